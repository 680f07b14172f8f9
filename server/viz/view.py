"""The 3D view's server: viser on its own port (it is not an ASGI app), fed by a thread at `rate_hz`.

Live mode reads the real-time worker's latest state (the seqlock in shared memory, via
`WorkerClient.latest_state()`), never the telemetry ring, so watching adds no load to the worker or
the session recorder. Replay mode plays a finished run's recorded telemetry (stance pose and slider
positions) in the same scene at its recorded speed. The view shows the robot's pose only, no patient
data, but it is a patient's session, so browsers reach it only through the console's login (proxy.py).
"""

from __future__ import annotations

import logging
import threading
import time
import urllib.parse
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from core.robot import TwinRobot
from server.viz.scene import TwinScene

logger = logging.getLogger(__name__)

DEFAULT_RATE_HZ = 30.0
MIN_RATE_HZ = 30.0  # issue 7: the view follows the robot at 30 Hz or more
# Camera presets: (position, look-at) in the world frame, m; x is where the patient faces, y their left.
CAMERA_PRESETS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "oblique": ((3.4, -3.4, 2.4), (0.0, 0.0, 0.6)),
    "front": ((4.2, 0.0, 1.2), (0.0, 0.0, 0.8)),
    "left": ((0.0, 4.2, 1.2), (0.0, 0.0, 0.8)),
    "right": ((0.0, -4.2, 1.2), (0.0, 0.0, 0.8)),
    "top": ((0.01, 0.0, 5.0), (0.0, 0.0, 0.0)),
}
DEFAULT_PRESET = "oblique"
PRESET_WORDS = {
    "oblique": "Overview",
    "front": "Front",
    "left": "Left side",
    "right": "Right side",
    "top": "From above",
}
# viser warns each browser on software WebGL (client/src/BrowserWarning.tsx); in the session page the
# console's own status line says how the view runs, so the notice is taken away again.
SOFTWARE_WEBGL_NOTICE = "webgl-software-rendering"
NOTICE_REMOVAL_DELAYS_S = (0.5, 2.0, 5.0)  # the browser shows it on mount, before or after connecting
# The console's relay (proxy.py) names the browser of each viser connection in this query parameter, so that
# viser's panel follows that browser's own engineering switch and a camera preset turns that browser's views.
VIEWER_PARAM = "viewer"
VIEWER_MAX_CHARS = 64


class ReplayError(ValueError):
    """A session log that cannot be replayed; names the column and what is wrong."""

    def __init__(self, field_name: str, value: object, limit: str) -> None:
        self.field, self.value, self.limit = field_name, value, limit
        super().__init__(f"{field_name} = {value!r}: {limit}")


def _finite_or(primary: Any, fallback: Any) -> np.ndarray:
    values = np.asarray(primary if primary is not None else fallback, dtype=float)
    return values if np.all(np.isfinite(values)) else np.asarray(fallback, dtype=float)


def pose_from_state(state: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(stance pose (6,), slider positions (12,)) to draw from the worker's latest state: the measured
    stance pose (forward kinematics of the measured sliders) so that rods meet the platform, else the command."""
    commanded = np.asarray(state["stance_pose"], dtype=float)
    stance = _finite_or(state.get("measured_stance_pose"), commanded)
    sliders = _finite_or(state.get("slider_position_m"), state.get("slider_command_m", np.zeros(12)))
    return stance, sliders


class Replay:
    """A recorded run resampled to the view's frame period: frame k shows the sample at k / rate_hz."""

    def __init__(self, run_id: int, columns: Mapping[str, np.ndarray], rate_hz: float) -> None:
        for name in ("time_s", "stance_pose", "slider_position_m"):
            if name not in columns:
                raise ReplayError(f"columns.{name}", None, "the session log has no such column")
        time_s = np.asarray(columns["time_s"], dtype=float)
        if len(time_s) < 2:
            raise ReplayError("columns.time_s", len(time_s), "needs at least 2 samples to replay")
        frame_times = time_s[0] + np.arange(0.0, time_s[-1] - time_s[0], 1.0 / rate_hz)
        rows = np.clip(np.searchsorted(time_s, frame_times), 0, len(time_s) - 1)
        stance = np.asarray(columns["stance_pose"], dtype=float)[rows]
        measured = columns.get("measured_stance_pose")
        if measured is not None:
            measured = np.asarray(measured, dtype=float)[rows]
            stance = np.where(np.isfinite(measured).all(axis=1, keepdims=True), measured, stance)
        self.run_id = run_id
        self.stance_poses = stance
        self.slider_positions_m = np.asarray(columns["slider_position_m"], dtype=float)[rows]
        self.duration_s = float(time_s[-1] - time_s[0])
        self.rate_hz = rate_hz
        self.frame = 0

    @property
    def finished(self) -> bool:
        return self.frame >= len(self.stance_poses)

    @property
    def position_s(self) -> float:
        return min(self.frame / self.rate_hz, self.duration_s)


class ViewPortTaken(RuntimeError):  # noqa: N818 — a state, not a malfunction
    """The configured port is in use: one robot gets one 3D view (issue 20, defect 19)."""


class LiveView:
    """The viser server, its `TwinScene`, and the thread that feeds it (live or replay)."""

    def __init__(
        self,
        twin: TwinRobot,
        latest_state: Callable[[], Mapping[str, Any]] | None,
        *,
        host: str = "127.0.0.1",
        port: int = 8081,
        rate_hz: float = DEFAULT_RATE_HZ,
    ) -> None:
        if not MIN_RATE_HZ <= rate_hz <= 120.0:
            raise ValueError(f"rate_hz = {rate_hz!r}: must be in [{MIN_RATE_HZ:g}, 120] Hz")
        self.twin, self.latest_state = twin, latest_state
        self.host, self.requested_port, self.rate_hz = host, port, rate_hz
        self._lock = threading.Lock()
        self._replay: Replay | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_shown: tuple[bytes, bytes] | None = None
        self.last_tick: int | None = None
        self.server: Any = None
        self.scene: TwinScene | None = None
        # Per browser (viewer): whose switch shows viser's panel, where each one looks from, and which viser
        # clients each one has open. The scene itself (robot, figure, labels) is shared by all.
        self._viewers_lock = threading.Lock()
        self._panel_viewers: set[str] = set()
        self._preset_of_viewer: dict[str, str] = {}
        self._viewer_of_client: dict[int, str | None] = {}

    def start(self) -> None:
        import viser

        self.server = viser.ViserServer(
            host=self.host, port=self.requested_port, label="ssp-rehab 3D view", verbose=False
        )
        if self.server.get_port() != self.requested_port:  # viser moves on to the next free port by itself
            moved = self.server.get_port()
            self.server.stop()
            self.server = None
            raise ViewPortTaken(
                f"the 3D view's port {self.requested_port} is taken (by another web process of this console, or "
                f"another program): this process serves no 3D view (viser would have opened a second one on {moved})"
            )
        self.server.gui.configure_theme(
            control_layout="floating", control_width="small", show_logo=False, show_share_button=False
        )
        position, look_at = CAMERA_PRESETS[DEFAULT_PRESET]  # every page opens on the overview, unless its
        self.server.initial_camera.position = position  # browser chose another preset (`_welcome`)
        self.server.initial_camera.look_at = look_at
        self.scene = TwinScene(self.server, self.twin)
        # The camera presets are the panel's content, so viser's developer controls (server address,
        # statistics, dev settings) stay behind its settings button instead of filling the panel.
        with self.server.gui.add_folder("Camera"):
            for preset, label in PRESET_WORDS.items():
                button = self.server.gui.add_button(label)
                button.on_click(lambda event, preset=preset: self._preset_clicked(event.client, preset))
        self.server.on_client_connect(self._hide_software_webgl_notice)
        # viser's panel is an engineering tool, shown only in the browsers whose switch is on. Each client gets
        # its own minimize/expand (client scope, one sender, so in order); a server-wide default as well would
        # race with it on connect (two senders: the later arrival wins in viser's page). Likewise its camera.
        self.server.on_client_connect(self._welcome)
        self.server.on_client_disconnect(self._forget_client)
        self._thread = threading.Thread(target=self._run, name="viz-feed", daemon=True)
        self._thread.start()
        logger.info("3D view on port %d at %.0f Hz", self.port, self.rate_hz)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(2.0)
        if self.server is not None:
            self.server.stop()

    @property
    def port(self) -> int:
        return int(self.server.get_port()) if self.server is not None else self.requested_port

    # --- camera, figure, notices -----------------------------------------------------------------------

    def set_camera(self, viewer: str, preset: str) -> None:
        """This viewer's open views, and the ones it opens later, look from this preset (a viewer is one
        browser's login: `proxy.viewer_of`); every other browser keeps its own camera."""
        if preset not in CAMERA_PRESETS:
            raise ValueError(f"preset = {preset!r}: must be one of {sorted(CAMERA_PRESETS)}")
        with self._viewers_lock:
            self._preset_of_viewer[viewer] = preset
            for client_id, client in self.server.get_clients().items():
                if self._viewer_of_client.get(client_id) == viewer:
                    self._aim(client, preset)

    def camera_preset(self, viewer: str | None) -> str:
        with self._viewers_lock:
            return self._preset_of(viewer)

    def _preset_of(self, viewer: str | None) -> str:  # with _viewers_lock held
        return self._preset_of_viewer.get(viewer, DEFAULT_PRESET) if viewer is not None else DEFAULT_PRESET

    def _preset_clicked(self, client: Any, preset: str) -> None:
        """A preset button of viser's own panel: the clicking browser's views turn (an unknown browser: only
        the view clicked in)."""
        if client is None:
            return
        with self._viewers_lock:
            viewer = self._viewer_of_client.get(client.client_id)
        if viewer is not None:
            self.set_camera(viewer, preset)
        else:
            self._aim(client, preset)

    @staticmethod
    def _aim(client: Any, preset: str) -> None:
        """Turns one viser client to a preset. Its own initial pose too, where viser's page returns on "Reset
        View" and when the scene's initial pose reaches a page just opened (so that cannot undo this turn)."""
        from viser._messages import SetCameraLookAtMessage, SetCameraPositionMessage  # no per-client API in 1.1

        position, look_at = CAMERA_PRESETS[preset]
        with client.atomic():
            try:
                client._websock_connection.queue_message(SetCameraPositionMessage(position, initial=True))
                client._websock_connection.queue_message(SetCameraLookAtMessage(look_at, initial=True))
            except AttributeError:  # viser changed its internals: the view still turns, "Reset View" goes back
                logger.warning("3D view: could not set viser client %s's own initial camera", client.client_id)
            client.camera.position = position
            client.camera.look_at = look_at

    def set_controls_visible(self, viewer: str, visible: bool) -> None:
        """Expands viser's control panel, or minimizes it to its title bar, in this viewer's open views and
        later ones; every other browser keeps its own."""
        with self._viewers_lock:
            if visible:
                self._panel_viewers.add(viewer)
            else:
                self._panel_viewers.discard(viewer)
            for client_id, client in self.server.get_clients().items():
                if self._viewer_of_client.get(client_id) == viewer:
                    self._show_panel(client, visible)

    def controls_visible(self, viewer: str | None) -> bool:
        with self._viewers_lock:
            return viewer in self._panel_viewers

    @staticmethod
    def _show_panel(client: Any, visible: bool) -> None:
        panel = client.gui.main_panel
        if visible:
            panel.expand()
        else:
            panel.minimize()

    def _welcome(self, client: Any) -> None:
        """A new viser client (a page opened or reloaded): its browser's panel and camera."""
        with self._viewers_lock:  # held while sending, so that a switch or preset at this moment lands after
            viewer = self._viewer_of_client[client.client_id] = self._viewer_of(client)
            self._show_panel(client, viewer in self._panel_viewers)
            preset = self._preset_of(viewer)
            if preset != DEFAULT_PRESET:  # the scene's initial pose is the overview already
                self._aim(client, preset)

    def _forget_client(self, client: Any) -> None:
        with self._viewers_lock:
            self._viewer_of_client.pop(client.client_id, None)

    def _viewer_of(self, client: Any) -> str | None:
        """The viewer the relay named in this connection's address (`/?viewer=...`); None: an unknown
        browser, whose panel stays minimized."""
        try:  # viser 1.1 keeps the upgrade request of each connection only in its websocket server
            request = self.server._websock_server._live_connections[client.client_id].request
            query = urllib.parse.urlsplit(request.path).query
        except (AttributeError, KeyError):
            logger.warning("3D view: could not tell which browser viser client %s is", client.client_id)
            return None
        viewers = urllib.parse.parse_qs(query).get(VIEWER_PARAM, [])
        return viewers[0] if len(viewers) == 1 and len(viewers[0]) <= VIEWER_MAX_CHARS else None

    def set_figure_height(self, height_m: float) -> bool:
        assert self.scene is not None
        return self.scene.set_figure_height(height_m)

    def _hide_software_webgl_notice(self, client: Any) -> None:
        from viser._messages import RemoveNotificationMessage  # no public switch for this notice in viser 1.1

        def remove() -> None:
            try:
                client._websock_connection.queue_message(RemoveNotificationMessage(SOFTWARE_WEBGL_NOTICE))
            except Exception:  # the browser left, or viser changed its internals: the notice stays, harmless
                logger.debug("3D view: could not remove the software-WebGL notice", exc_info=True)

        for delay_s in NOTICE_REMOVAL_DELAYS_S:
            timer = threading.Timer(delay_s, remove)
            timer.daemon = True
            timer.start()

    # --- modes -------------------------------------------------------------------------------------

    def replay(self, run_id: int, columns: Mapping[str, np.ndarray]) -> Replay:
        replay = Replay(run_id, columns, self.rate_hz)
        with self._lock:
            self._replay = replay
        return replay

    def go_live(self) -> None:
        with self._lock:
            self._replay = None
            self._last_shown = None

    def status(self, viewer: str | None = None) -> dict[str, Any]:
        """The view's state; `controls_visible` and `camera_preset` are this viewer's (None: no browser's)."""
        with self._lock:
            replay = self._replay
        scene = self.scene
        status: dict[str, Any] = {
            "available": scene is not None,
            "port": self.port,
            "rate_hz": self.rate_hz,
            "mode": "live" if replay is None else "replay",
            "frames_shown": scene.frames_shown if scene is not None else 0,
            "last_tick": self.last_tick,
            "robot_connected": self.latest_state is not None,
            "camera_preset": self.camera_preset(viewer),
            "controls_visible": self.controls_visible(viewer),
            "camera_presets": list(CAMERA_PRESETS),
            "figure_height_m": scene.figure_height_m if scene is not None else None,
        }
        if replay is not None:
            status.update(
                replay_run_id=replay.run_id,
                replay_position_s=round(replay.position_s, 3),
                replay_duration_s=round(replay.duration_s, 3),
                replay_finished=replay.finished,
            )
        return status

    # --- the feed ----------------------------------------------------------------------------------

    def step(self) -> bool:
        """Show one frame (live or replay); False when there was nothing new to show."""
        assert self.scene is not None
        with self._lock:
            replay = self._replay
        if replay is not None:
            if replay.finished:
                return False
            self.scene.show(replay.stance_poses[replay.frame], replay.slider_positions_m[replay.frame])
            replay.frame += 1
            return True
        if self.latest_state is None:
            return False
        state = self.latest_state()
        if not state:
            return False  # the robot daemon is not attached yet (starting, or gone)
        stance, sliders = pose_from_state(state)
        key = (stance.tobytes(), sliders.tobytes())
        if key == self._last_shown:
            return False  # the robot stands still: nothing to send to the browsers
        self._last_shown = key
        self.last_tick = int(state.get("tick", 0))
        self.scene.show(stance, sliders)
        return True

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        next_frame = time.monotonic()
        while not self._stop.is_set():
            try:
                self.step()
            except Exception:
                logger.exception("3D view: one frame failed")
            next_frame += period
            delay = next_frame - time.monotonic()
            if delay < -period:
                next_frame = time.monotonic()  # fell behind (a busy machine): skip ahead, never burst
            self._stop.wait(max(0.0, delay))


def start_view(settings: Any, twin: TwinRobot, worker: Any) -> LiveView | None:
    """The 3D view for the service, or None (logged) when it is turned off or cannot listen."""
    if not settings.viz_enabled:
        return None
    view = LiveView(
        twin,
        worker.latest_state if worker is not None else None,
        host=settings.viz_host,
        port=settings.viz_port,
        rate_hz=settings.viz_rate_hz,
    )
    try:
        view.start()
    except ViewPortTaken as taken:
        logger.info("%s", taken)
        view.stop()
        return None
    except Exception:
        logger.exception(
            "the 3D view did not start on %s:%d: the console runs without it", settings.viz_host, settings.viz_port
        )
        view.stop()
        return None
    return view
