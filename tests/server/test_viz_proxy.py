"""Issue 12, defect 13: the 3D view shows a patient's session, so only logged-in users may watch it.
viser listens on loopback only and the console relays its page and WebSocket behind the login."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator
from typing import Any

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


def viser_messages(frame: bytes) -> list[dict[str, Any]]:
    """The messages in one frame viser sent: sizes (8 + 8 bytes, little-endian), then zstd-compressed msgpack."""
    import msgspec
    import zstandard

    size, compressed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(frame[16 : 16 + compressed], max_output_size=size)
    return list(msgspec.msgpack.decode(inner)["messages"])


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
        # The camera as viser's page places it (m, world frame): the first initial pose resets it (its
        # InitialCameraSetter), later initial poses only change where "Reset View" goes, a move moves it.
        self.camera: tuple[float, ...] | None = None
        self.initial_camera: tuple[float, ...] | None = None

    def read(self, quiet_s: float = 1.0) -> bool:
        """Takes in what viser sent until it has been quiet for `quiet_s` (s); True when the panel is minimized."""
        while True:
            try:
                frame = self.socket.recv(timeout=quiet_s)
            except TimeoutError:
                return self.collapsed
            assert isinstance(frame, bytes)
            for message in viser_messages(frame):
                if message["type"] == "SetCameraPositionMessage":
                    self._place_camera(tuple(message["position"]), initial=bool(message["initial"]))
                if message["type"] != "GuiSetPanelCollapsedMessage" or message["uuid"] != "viser-control-panel":
                    continue
                if message["counter"] > self._applied.get(message["run_id"], 0):
                    self._applied[message["run_id"]] = message["counter"]
                    self.collapsed = bool(message["collapsed"])

    def _place_camera(self, position: tuple[float, ...], *, initial: bool) -> None:
        if initial:
            if self.initial_camera is None:
                self.camera = position
            self.initial_camera = position
        else:
            self.camera = position

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


class ThreeBrowsers:
    """The console under uvicorn with the view, and three browsers' viser clients through its relay: the
    therapist's tablet and wall screen (one account, two logins) and a colleague."""

    def __init__(self, base_url: str, view: LiveView) -> None:
        self.base_url, self.view = base_url, view
        self.tokens = {"tablet": _login(base_url, "therapist", THERAPIST_PASSWORD),
                       "wall": _login(base_url, "therapist", THERAPIST_PASSWORD),
                       "colleague": _login(base_url, "admin", ADMIN_PASSWORD)}  # fmt: skip
        self.browsers: dict[str, ViserBrowser] = {}
        self.reload(*self.tokens)

    def reload(self, *names: str) -> None:
        """A (re)load of these browsers' pages: each is a new viser client."""
        for name in names:
            if name in self.browsers:
                self.browsers[name].close()
            self.browsers[name] = ViserBrowser(self.base_url, self.tokens[name])
        _wait_for_clients(self.view, len(self.tokens))

    def post(self, name: str, path: str, body: dict[str, object]) -> httpx.Response:
        return httpx.post(f"{self.base_url}/api/v1{path}", json=body, headers={**_bearer(self.tokens[name]), **CSRF})

    def status(self, name: str) -> dict[str, object]:
        return dict(httpx.get(f"{self.base_url}/api/v1/viz", headers=_bearer(self.tokens[name])).json())


# What a browser's view shows does not depend on the database; each of these takes ~16 s of viser traffic.
ONE_DATABASE = pytest.mark.parametrize("migrated", ["sqlite"], indirect=True)


@pytest.fixture
def three_browsers(settings: Settings, database: Database, view: LiveView) -> Iterator[ThreeBrowsers]:
    app = create_app(settings, database=database, worker=None)
    with live_server(app) as base_url:
        app.state.viz = view
        clinic = ThreeBrowsers(base_url, view)
        try:
            yield clinic
        finally:
            for browser in clinic.browsers.values():
                browser.close()


@ONE_DATABASE
def test_the_engineering_switch_shows_visers_panel_in_that_browser_only(three_browsers: ThreeBrowsers) -> None:
    """The therapist's tablet turns the switch on: the wall screen (the same account, another login) and
    another therapist keep the panel minimized, also when they reload; the tablet's reload shows it again."""
    clinic, browsers = three_browsers, three_browsers.browsers
    assert all(browser.read() for browser in browsers.values()), "viser's panel shows before any switch"
    switched = clinic.post("tablet", "/viz/controls", {"visible": True})
    assert switched.status_code == 200, switched.text
    assert switched.json()["controls_visible"] is True
    shown = {name: not browser.read() for name, browser in browsers.items()}
    assert shown == {"tablet": True, "wall": False, "colleague": False}
    statuses = {name: clinic.status(name)["controls_visible"] for name in ("tablet", "wall")}
    assert statuses == {"tablet": True, "wall": False}
    clinic.reload("tablet", "wall")
    shown = {name: not browser.read() for name, browser in browsers.items()}
    assert shown == {"tablet": True, "wall": False, "colleague": False}
    clinic.post("tablet", "/viz/controls", {"visible": False})
    assert all(browser.read() for browser in browsers.values())


# --- issue 16 §3, 3D view: a camera preset moves the asking browser's views only ------------------------


def preset_at(position: tuple[float, ...] | None, tolerance_m: float) -> str | None:
    """The camera preset whose position this is, within `tolerance_m` (m) on each axis; None: none of them."""
    from server.viz.view import CAMERA_PRESETS

    if position is None:
        return None
    return next((name for name, (at, _) in CAMERA_PRESETS.items()
                 if max(abs(a - b) for a, b in zip(position, at, strict=True)) <= tolerance_m), None)  # fmt: skip


def _looks_from(browsers: dict[str, ViserBrowser]) -> dict[str, str | None]:
    """Which preset each browser's camera stands at, once it has read what viser sent."""
    for browser in browsers.values():
        browser.read()
    return {name: preset_at(browser.camera, 1e-6) for name, browser in browsers.items()}


@ONE_DATABASE
def test_a_camera_preset_moves_the_camera_of_that_browser_only(three_browsers: ThreeBrowsers) -> None:
    """The therapist's tablet looks from the front: the wall screen (the same account, another login) and a
    colleague keep the overview, also when they reload; the tablet's reload looks from the front again."""
    clinic, browsers = three_browsers, three_browsers.browsers
    assert _looks_from(browsers) == {"tablet": "oblique", "wall": "oblique", "colleague": "oblique"}
    moved = clinic.post("tablet", "/viz/camera", {"preset": "front"})
    assert moved.status_code == 200, moved.text
    assert moved.json()["camera_preset"] == "front"
    assert _looks_from(browsers) == {"tablet": "front", "wall": "oblique", "colleague": "oblique"}
    presets = {name: clinic.status(name)["camera_preset"] for name in browsers}
    assert presets == {"tablet": "front", "wall": "oblique", "colleague": "oblique"}
    clinic.reload("tablet", "wall", "colleague")
    assert _looks_from(browsers) == {"tablet": "front", "wall": "oblique", "colleague": "oblique"}
    clinic.post("colleague", "/viz/camera", {"preset": "top"})
    assert _looks_from(browsers) == {"tablet": "front", "wall": "oblique", "colleague": "top"}


def test_camera_presets_need_a_login_and_a_known_preset(viz_client: TestClient, seed: Seed) -> None:
    """Only a logged-in user turns a view, only its own (no viewer can be named), and only to a preset."""
    assert viz_client.post("/api/v1/viz/camera", json={"preset": "front"}, headers=CSRF).status_code == 401
    for body in ({"preset": "behind"}, {"preset": "front", "viewer": "0" * 32}):
        refused = viz_client.post("/api/v1/viz/camera", json=body, headers={**seed.headers(), **CSRF})
        assert refused.status_code == 422, refused.text
        assert ("preset" if body["preset"] == "behind" else "viewer") in refused.text, refused.text
