"""Issue 12, defect 13: the 3D view shows a patient's session, so only logged-in users may watch it.
viser listens on loopback only and the console relays its page and WebSocket behind the login."""

from __future__ import annotations

import socket
from collections.abc import Iterator

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from starlette.websockets import WebSocketDisconnect

from core.robot import default_twin
from server.app import create_app
from server.db import Database
from server.settings import Settings
from server.viz.view import LiveView
from tests.server.conftest import Seed


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@pytest.fixture
def view() -> Iterator[LiveView]:
    live = LiveView(default_twin(), None, port=_free_port())
    live.start()
    yield live
    live.stop()


@pytest.fixture
def viz_client(settings: Settings, database: Database, view: LiveView) -> Iterator[TestClient]:
    with TestClient(create_app(settings, database=database, worker=None)) as test_client:
        test_client.app.state.viz = view  # type: ignore[attr-defined]
        yield test_client


@pytest.mark.parametrize("host", ["0.0.0.0", "192.168.1.20", "::", "robot.clinic.example"])
def test_viser_may_listen_on_loopback_only(host: str) -> None:
    with pytest.raises(ValidationError, match=r"viz_host = .*must be a loopback address"):
        Settings(_env_file=None, viz_host=host)  # type: ignore[call-arg]


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "::1", "localhost"])
def test_loopback_hosts_are_accepted(host: str) -> None:
    assert Settings(_env_file=None, viz_host=host).viz_host == host  # type: ignore[call-arg]


def test_view_page_needs_a_login(viz_client: TestClient, seed: Seed) -> None:
    assert viz_client.get("/api/v1/viz/view/").status_code == 401
    page = viz_client.get("/api/v1/viz/view/", headers=seed.headers())
    assert page.status_code == 200, page.text[:200]
    assert page.headers["content-type"].startswith("text/html")
    assert "<script" in page.text  # viser's own page, relayed from its loopback port
    assert "frame-ancestors 'self'" in page.headers["content-security-policy"]


def test_view_socket_refuses_anonymous_watchers(viz_client: TestClient) -> None:
    with pytest.raises(WebSocketDisconnect) as refused, viz_client.websocket_connect("/api/v1/viz/view") as socket_:
        socket_.receive_bytes()
    assert refused.value.code == 1008


def test_view_socket_relays_viser_to_a_logged_in_user(viz_client: TestClient, seed: Seed) -> None:
    import viser

    with viz_client.websocket_connect(
        "/api/v1/viz/view", headers=seed.headers(), subprotocols=[f"viser-v{viser.__version__}"]
    ) as socket_:
        first = socket_.receive_bytes()  # viser sends the scene as soon as a client is accepted
    assert len(first) > 0
