"""Issue 12, defect 13: the 3D view shows a patient's session, so only logged-in users may watch it.
viser listens on loopback only and the console relays its page and WebSocket behind the login."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator

import httpx
import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError
from starlette.websockets import WebSocketDisconnect

from core.robot import default_twin
from server.app import create_app
from server.db import Database
from server.settings import Settings
from server.viz.view import LiveView
from tests.server.conftest import ADMIN_PASSWORD, THERAPIST_PASSWORD, Seed
from tests.server.test_web_security import CSRF_HEADERS as CSRF
from tests.server.test_web_security import live_server


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


# --- issue 16, 3D view: viser's panel follows each browser's own engineering switch ------------------


class ViserBrowser:
    """One browser's viser client behind the console's relay: it says where its camera is (viser counts a
    client as connected from then on) and mirrors viser's control panel as viser's page does (per axis and
    per sender run: a placement command applies when its counter is above that run's last one)."""

    def __init__(self, base_url: str, token: str) -> None:
        import viser
        from viser import _messages
        from websockets.sync.client import connect

        self.socket = connect(
            base_url.replace("http://", "ws://") + "/api/v1/viz/view",
            additional_headers={"Authorization": f"Bearer {token}"},
            subprotocols=[f"viser-v{viser.__version__}"],  # type: ignore[list-item]
            max_size=None,
        )
        camera = _messages.ViewerCameraMessage(
            wxyz=(1.0, 0.0, 0.0, 0.0), position=(3.4, -3.4, 2.4), fov=1.0, near=0.01, far=100.0,
            image_height=768, image_width=1024, look_at=(0.0, 0.0, 0.6), up_direction=(0.0, 0.0, 1.0),
        )  # fmt: skip
        import msgspec

        self.socket.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
        self.collapsed = False  # viser's page shows its panel expanded until told otherwise
        self._applied: dict[str, int] = {}

    def read(self, quiet_s: float = 1.0) -> bool:
        """Takes in what viser sent until it has been quiet for `quiet_s` (s); True when the panel is minimized."""
        import msgspec
        import zstandard

        while True:
            try:
                frame = self.socket.recv(timeout=quiet_s)
            except TimeoutError:
                return self.collapsed
            assert isinstance(frame, bytes)
            size, compressed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
            inner = zstandard.ZstdDecompressor().decompress(frame[16 : 16 + compressed], max_output_size=size)
            for message in msgspec.msgpack.decode(inner)["messages"]:
                if message["type"] != "GuiSetPanelCollapsedMessage" or message["uuid"] != "viser-control-panel":
                    continue
                if message["counter"] > self._applied.get(message["run_id"], 0):
                    self._applied[message["run_id"]] = message["counter"]
                    self.collapsed = bool(message["collapsed"])

    def close(self) -> None:
        self.socket.close()


def _login(base_url: str, username: str, password: str) -> str:
    response = httpx.post(f"{base_url}/api/v1/auth/login", json={"username": username, "password": password})
    assert response.status_code == 200, response.text
    return str(response.json()["access_token"])


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def _wait_for_clients(view: LiveView, count: int) -> None:
    for _ in range(100):
        if len(view.server.get_clients()) >= count:
            return
        time.sleep(0.05)
    raise AssertionError(f"viser saw {len(view.server.get_clients())} clients, not {count}")


def test_the_engineering_switch_shows_visers_panel_in_that_browser_only(
    settings: Settings, database: Database, view: LiveView
) -> None:
    """The therapist's tablet turns the switch on: the wall screen (the same account, another login) and
    another therapist keep the panel minimized, also when they reload; the tablet's reload shows it again."""
    app = create_app(settings, database=database, worker=None)
    with live_server(app) as base_url:
        app.state.viz = view
        tablet, wall = (_login(base_url, "therapist", THERAPIST_PASSWORD) for _device in range(2))
        colleague = _login(base_url, "admin", ADMIN_PASSWORD)
        browsers = {name: ViserBrowser(base_url, token) for name, token in
                    (("tablet", tablet), ("wall", wall), ("colleague", colleague))}  # fmt: skip
        try:
            _wait_for_clients(view, 3)
            assert all(browser.read() for browser in browsers.values()), "viser's panel shows before any switch"
            switched = httpx.post(f"{base_url}/api/v1/viz/controls", json={"visible": True},
                                  headers={**_bearer(tablet), **CSRF})  # fmt: skip
            assert switched.status_code == 200, switched.text
            assert switched.json()["controls_visible"] is True
            shown = {name: not browser.read() for name, browser in browsers.items()}
            assert shown == {"tablet": True, "wall": False, "colleague": False}
            statuses = {name: httpx.get(f"{base_url}/api/v1/viz", headers=_bearer(token)).json()["controls_visible"]
                        for name, token in (("tablet", tablet), ("wall", wall))}  # fmt: skip
            assert statuses == {"tablet": True, "wall": False}
            for name, token in (("tablet", tablet), ("wall", wall)):  # a reload is a new viser client
                browsers[name].close()
                browsers[name] = ViserBrowser(base_url, token)
            _wait_for_clients(view, 3)
            shown = {name: not browser.read() for name, browser in browsers.items()}
            assert shown == {"tablet": True, "wall": False, "colleague": False}
            httpx.post(f"{base_url}/api/v1/viz/controls", json={"visible": False},
                       headers={**_bearer(tablet), **CSRF})  # fmt: skip
            assert all(browser.read() for browser in browsers.values())
        finally:
            for browser in browsers.values():
                browser.close()
