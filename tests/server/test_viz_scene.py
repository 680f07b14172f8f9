"""The 3D view (server/viz): geometry that puts every rod between its slider and its platform joint, a scene
whose nodes are created once and then only moved (inside `atomic()`), the live feed and the replay of a log."""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np
import pytest

from core.kinematics import twin_inverse_kinematics
from core.robot import default_twin
from server.viz.scene import TwinGeometry, TwinScene, wxyz_from_matrices, wxyz_z_to
from server.viz.view import LiveView, Replay, ReplayError, pose_from_state

TWIN = default_twin()
POSES = np.array(
    [
        [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [0.03, -0.05, 0.02, 0.05, -0.04, 0.03],
        [-0.04, 0.06, -0.03, -0.06, 0.05, -0.08],
    ]
)


def _sliders(stance_pose: np.ndarray) -> np.ndarray:
    solutions = twin_inverse_kinematics(TWIN, stance_pose[None, :])
    return np.concatenate([solutions[side].slider_positions_m[0] for side in TWIN.sides])


def _rotate(wxyz: np.ndarray, vector: np.ndarray) -> np.ndarray:
    w, xyz = wxyz[0], wxyz[1:]
    return vector + 2.0 * np.cross(xyz, np.cross(xyz, vector) + w * vector)


@pytest.mark.parametrize("stance_pose", POSES)
def test_every_rod_spans_its_slider_and_platform_joint(stance_pose: np.ndarray) -> None:
    """With IK slider positions, each of the 12 rods is exactly the rod length: the world transforms are right."""
    pose = TwinGeometry(TWIN).pose(stance_pose, _sliders(stance_pose))
    lengths = np.linalg.norm(pose.platform_joints_m - pose.slider_joints_m, axis=1)
    np.testing.assert_allclose(lengths, TWIN.robot.rod_length_m, atol=1e-9)


def test_wrong_slider_positions_break_the_rods() -> None:
    """The check above can fail: sliders 5 cm off leave rods of the wrong length."""
    stance = POSES[1]
    pose = TwinGeometry(TWIN).pose(stance, _sliders(stance) + 0.05)
    lengths = np.linalg.norm(pose.platform_joints_m - pose.slider_joints_m, axis=1)
    assert np.all(np.abs(lengths - TWIN.robot.rod_length_m) > 1e-3)


def test_stance_translation_moves_both_platforms_and_the_patient_together() -> None:
    geometry = TwinGeometry(TWIN)
    neutral = geometry.pose(np.zeros(6), geometry.neutral_sliders_m)
    shift = np.array([0.02, -0.03, 0.01, 0.0, 0.0, 0.0])
    moved = geometry.pose(shift, _sliders(shift))
    np.testing.assert_allclose(moved.platform_positions_m - neutral.platform_positions_m, [shift[:3]] * 2, atol=1e-12)
    np.testing.assert_allclose(moved.stance_position_m - neutral.stance_position_m, shift[:3], atol=1e-12)


@pytest.mark.parametrize(
    "direction", [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.3, 0.4, 0.5], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]
)
def test_cylinder_quaternion_lays_z_along_the_rod(direction: list[float]) -> None:
    d = np.asarray(direction) / np.linalg.norm(direction)
    q = wxyz_z_to(d[None, :])[0]
    np.testing.assert_allclose(np.linalg.norm(q), 1.0)
    np.testing.assert_allclose(_rotate(q, np.array([0.0, 0.0, 1.0])), d, atol=1e-12)


def test_platform_quaternion_matches_its_rotation_matrix() -> None:
    pose = TwinGeometry(TWIN).pose(POSES[2], _sliders(POSES[2]))
    quaternions = wxyz_from_matrices(pose.platform_rotations)
    for q, rotation in zip(quaternions, pose.platform_rotations, strict=True):
        for axis in np.eye(3):
            np.testing.assert_allclose(_rotate(q, axis), rotation @ axis, atol=1e-12)


# --- the scene, with a recording stand-in for viser -------------------------------------------------


class RecordingHandle:
    def __init__(self, server: RecordingServer, name: str) -> None:
        object.__setattr__(self, "_server", server)
        object.__setattr__(self, "name", name)

    def __setattr__(self, attribute: str, value: Any) -> None:
        self._server.assignments.append((self.name, attribute, self._server.in_atomic))
        object.__setattr__(self, attribute, np.asarray(value))

    def remove(self) -> None:
        self._server.removed.append((self.name, self._server.in_atomic))


class RecordingScene:
    def __init__(self, server: RecordingServer) -> None:
        self.server = server

    def __getattr__(self, method: str) -> Any:
        if not method.startswith("add_"):
            raise AttributeError(method)

        def add(name: str, *args: Any, **kwargs: Any) -> RecordingHandle:
            self.server.added.append((method, name))
            self.server.arguments[name] = (args, kwargs)
            return RecordingHandle(self.server, name)

        return add


class RecordingServer:
    def __init__(self) -> None:
        self.added: list[tuple[str, str]] = []
        self.arguments: dict[str, tuple[tuple[Any, ...], dict[str, Any]]] = {}
        self.removed: list[tuple[str, bool]] = []
        self.assignments: list[tuple[str, str, bool]] = []
        self.in_atomic = False
        self.scene = RecordingScene(self)

    def get_port(self) -> int:
        return 8081

    @contextlib.contextmanager
    def atomic(self) -> Any:
        self.in_atomic = True
        try:
            yield
        finally:
            self.in_atomic = False


def test_scene_nodes_are_created_once_and_then_only_moved_atomically() -> None:
    server = RecordingServer()
    scene = TwinScene(server, TWIN)
    created = list(server.added)
    kinds = [kind for kind, _ in created]
    assert kinds.count("add_box") >= 12 + 2  # sliders, foot plates
    assert kinds.count("add_cylinder") >= 12 + 6  # rods, rails
    assert len({name for _, name in created}) == len(created)  # every node has its own name
    server.assignments.clear()
    for stance in POSES:
        scene.show(stance, _sliders(stance))
    assert server.added == created  # nothing added after construction
    assert server.assignments and all(in_atomic for _, _, in_atomic in server.assignments)
    assert {attribute for _, attribute, _ in server.assignments} == {"position", "wxyz"}
    assert scene.frames_shown == 1 + len(POSES)


def test_scene_shows_the_pose_it_is_given() -> None:
    server = RecordingServer()
    scene = TwinScene(server, TWIN)
    stance = POSES[1]
    sliders = _sliders(stance)
    scene.show(stance, sliders)
    expected = TwinGeometry(TWIN).pose(stance, sliders)
    np.testing.assert_allclose(np.array([s.position for s in scene.sliders]), expected.slider_joints_m)
    np.testing.assert_allclose(np.array([p.position for p in scene.platforms]), expected.platform_positions_m)
    # Each rod's centre lies half a rod length from its slider, towards the platform joint.
    centres = np.array([rod.position for rod in scene.rods])
    np.testing.assert_allclose(np.linalg.norm(centres - expected.slider_joints_m, axis=1), TWIN.robot.rod_length_m / 2)


# --- the feed: live and replay ----------------------------------------------------------------------


def _view_with(state: dict[str, Any] | None) -> tuple[LiveView, RecordingServer]:
    view = LiveView(TWIN, (lambda: state) if state is not None else None, rate_hz=50.0)
    server = RecordingServer()
    view.server, view.scene = server, TwinScene(server, TWIN)
    return view, server


def _state(stance: np.ndarray, tick: int) -> dict[str, Any]:
    return {"tick": tick, "stance_pose": stance.tolist(), "measured_stance_pose": stance.tolist(),
            "slider_position_m": _sliders(stance).tolist()}  # fmt: skip


def test_live_feed_shows_new_states_and_skips_unchanged_ones() -> None:
    state = _state(POSES[1], 10)
    view, _ = _view_with(state)
    shown = view.scene.frames_shown
    assert view.step() is True
    assert view.step() is False  # the robot stands still: nothing is sent
    state.update(_state(POSES[2], 11))
    assert view.step() is True
    assert view.scene.frames_shown == shown + 2
    assert view.last_tick == 11


def test_measured_pose_is_drawn_unless_forward_kinematics_failed() -> None:
    state = _state(POSES[1], 1)
    state["measured_stance_pose"] = [float("nan")] * 6
    stance, _ = pose_from_state(state)
    np.testing.assert_array_equal(stance, POSES[1])
    state["measured_stance_pose"] = POSES[2].tolist()
    np.testing.assert_array_equal(pose_from_state(state)[0], POSES[2])


def _log(duration_s: float, rate_hz: float) -> dict[str, np.ndarray]:
    time_s = 5.0 + np.arange(round(duration_s * rate_hz)) / rate_hz
    stance = np.zeros((len(time_s), 6))
    stance[:, 1] = 0.05 * np.sin(2 * np.pi * 0.5 * time_s)
    sliders = np.concatenate(
        [twin_inverse_kinematics(TWIN, stance)[side].slider_positions_m for side in TWIN.sides], axis=1
    )
    return {"time_s": time_s, "stance_pose": stance, "slider_position_m": sliders}


def test_replay_plays_the_log_at_its_recorded_speed_then_stops() -> None:
    log = _log(2.0, 1000.0)
    view, _ = _view_with(None)
    replay = view.replay(7, log)
    assert len(replay.stance_poses) == pytest.approx(2.0 * 50.0, abs=1)
    frames = 0
    while view.step():
        frames += 1
        shown = replay.stance_poses[replay.frame - 1]
        # Frame k shows the sample recorded at k / 50 s: row 20 k of the 1 kHz log (±1 for rounding).
        candidates = log["stance_pose"][[20 * (replay.frame - 1), min(20 * (replay.frame - 1) + 1, 1999)]]
        assert any(np.array_equal(shown, row) for row in candidates)
    assert frames == len(replay.stance_poses)
    assert view.status()["mode"] == "replay" and view.status()["replay_finished"] is True
    view.go_live()
    assert view.status()["mode"] == "live"


@pytest.mark.parametrize("missing", ["time_s", "stance_pose", "slider_position_m"])
def test_a_log_without_a_needed_column_is_refused_by_name(missing: str) -> None:
    log = _log(0.5, 100.0)
    del log[missing]
    with pytest.raises(ReplayError, match=missing):
        Replay(1, log, 50.0)


def test_the_view_refuses_a_rate_below_30_hz() -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        LiveView(TWIN, None, rate_hz=20.0)


# --- issue 16: labels, a figure of the patient's height, camera presets -----------------------------


def test_front_left_and_right_are_labelled() -> None:
    server = RecordingServer()
    TwinScene(server, TWIN)
    labels = {name: server.arguments[name] for method, name in server.added if method == "add_label"}
    texts = {args[0]: kwargs["position"] for args, kwargs in labels.values()}
    front = next(position for text, position in texts.items() if text.startswith("FRONT"))
    left = next(position for text, position in texts.items() if text.startswith("LEFT"))
    right = next(position for text, position in texts.items() if text.startswith("RIGHT"))
    assert front[0] > 0.5 and left[1] > 0.5 and right[1] < -0.5  # x forward, y to the patient's left


def _head_top(server: RecordingServer) -> float:
    _, kwargs = server.arguments["/twin/patient/head"]
    return float(kwargs["position"][2] + kwargs["radius"])


def test_the_figure_takes_the_patients_height_and_is_rebuilt_only_on_a_change() -> None:
    server = RecordingServer()
    scene = TwinScene(server, TWIN)
    generic_top = _head_top(server)
    assert scene.set_figure_height(1.92) is True
    assert len(server.removed) == len(scene.figure_parts) and all(atomic for _, atomic in server.removed)
    tall_top = _head_top(server)
    assert tall_top > generic_top + 0.15  # 22 cm taller, the head with it
    assert scene.set_figure_height(1.92) is False and len(server.removed) == len(scene.figure_parts)
    scene.set_figure_height(1.50)
    assert _head_top(server) < generic_top
    with pytest.raises(ValueError, match="height_m"):
        scene.set_figure_height(3.0)


class RecordingCamera:
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    look_at: tuple[float, float, float] = (0.0, 0.0, 0.0)


class RecordingPanel:
    def __init__(self) -> None:
        self.calls: list[str] = []

    def minimize(self) -> None:
        self.calls.append("minimize")

    def expand(self) -> None:
        self.calls.append("expand")


class RecordingConnection:
    def __init__(self) -> None:
        self.queued: list[Any] = []

    def queue_message(self, message: Any) -> None:
        self.queued.append(message)


class ViewClient:
    """A viser client as the view sees it: its id, its own panel and camera, and the address the relay
    opened it with."""

    def __init__(self, client_id: int, path: str) -> None:
        self.client_id, self.path = client_id, path
        self.gui = type("Gui", (), {"main_panel": RecordingPanel()})()
        self.camera = RecordingCamera()
        self._websock_connection = RecordingConnection()

    @contextlib.contextmanager
    def atomic(self) -> Any:
        yield


def _view_with_clients(paths: dict[int, str]) -> tuple[LiveView, dict[int, ViewClient]]:
    """A view whose viser server has these clients (id: the relay's address), each welcomed on connect."""
    view, server = _view_with(None)
    clients: dict[int, ViewClient] = {}
    connections: dict[int, Any] = {}
    server.get_clients = lambda: clients  # type: ignore[attr-defined]
    server.initial_camera = RecordingCamera()  # type: ignore[attr-defined]  # the scene's, shared by all pages
    server._websock_server = type("Websock", (), {"_live_connections": connections})()  # type: ignore[attr-defined]
    for client_id, path in paths.items():
        _connect(view, clients, client_id, path)
    return view, clients


def _connect(view: LiveView, clients: dict[int, ViewClient], client_id: int, path: str) -> ViewClient:
    client = clients[client_id] = ViewClient(client_id, path)
    request = type("Request", (), {"path": path})()
    view.server._websock_server._live_connections[client_id] = type("Connection", (), {"request": request})()
    view._welcome(client)
    return client


def test_a_camera_preset_turns_that_viewers_views_only_and_its_later_ones() -> None:
    from server.viz.view import CAMERA_PRESETS

    view, clients = _view_with_clients({1: "/?viewer=tablet", 2: "/?viewer=tablet", 3: "/?viewer=wall", 4: "/"})
    view.set_camera("tablet", "front")
    front = CAMERA_PRESETS["front"]
    untouched = (RecordingCamera.position, RecordingCamera.look_at)
    cameras = {i: (c.camera.position, c.camera.look_at) for i, c in clients.items()}
    assert cameras == {1: front, 2: front, 3: untouched, 4: untouched}
    # "Reset View" of the tablet's pages goes back to its preset too; nobody else's initial pose changes.
    initial = [(type(m).__name__, m.initial) for m in clients[1]._websock_connection.queued]
    assert initial[:2] == [("SetCameraPositionMessage", True), ("SetCameraLookAtMessage", True)]
    assert clients[3]._websock_connection.queued == [] and clients[4]._websock_connection.queued == []
    assert view.server.initial_camera.position == RecordingCamera.position  # the shared initial pose stays
    assert (view.status("tablet")["camera_preset"], view.status("wall")["camera_preset"]) == ("front", "oblique")
    assert view.status()["camera_preset"] == "oblique"  # no viewer named: nobody's preset
    reloaded = _connect(view, clients, 5, "/?viewer=tablet")
    wall_reloaded = _connect(view, clients, 6, "/?viewer=wall")
    assert (reloaded.camera.position, reloaded.camera.look_at) == front
    assert (wall_reloaded.camera.position, wall_reloaded.camera.look_at) == untouched
    assert wall_reloaded._websock_connection.queued == []  # the scene's initial pose is the overview already
    assert front[0][0] > abs(front[0][1]) and CAMERA_PRESETS["left"][0][1] > abs(CAMERA_PRESETS["left"][0][0])
    with pytest.raises(ValueError, match="preset"):
        view.set_camera("tablet", "behind")


def test_visers_own_preset_buttons_turn_the_clicking_browsers_views_only() -> None:
    from server.viz.view import CAMERA_PRESETS

    view, clients = _view_with_clients({1: "/?viewer=tablet", 2: "/?viewer=tablet", 3: "/?viewer=wall", 4: "/"})
    view._preset_clicked(clients[3], "top")
    view._preset_clicked(clients[4], "left")  # a browser the relay did not name: the page clicked in only
    view._preset_clicked(None, "right")  # no clicking client: nothing turns
    positions = {i: c.camera.position for i, c in clients.items()}
    top, left = CAMERA_PRESETS["top"][0], CAMERA_PRESETS["left"][0]
    assert positions == {1: RecordingCamera.position, 2: RecordingCamera.position, 3: top, 4: left}
    assert view.status("wall")["camera_preset"] == "top" and view.status("tablet")["camera_preset"] == "oblique"


def test_visers_panel_follows_each_viewers_own_engineering_switch() -> None:
    view, clients = _view_with_clients({1: "/?viewer=tablet", 2: "/?viewer=wall", 3: "/"})
    view.set_controls_visible("tablet", True)
    _connect(view, clients, 4, "/?viewer=tablet")  # the tablet reloads its page
    view.set_controls_visible("tablet", False)
    calls = {i: c.gui.main_panel.calls for i, c in clients.items()}
    assert calls == {1: ["minimize", "expand", "minimize"], 2: ["minimize"], 3: ["minimize"], 4: ["expand", "minimize"]}
    view.set_controls_visible("wall", True)
    assert view.status("wall")["controls_visible"] and not view.status("tablet")["controls_visible"]
    assert not view.status()["controls_visible"]  # no viewer named: nobody's switch
