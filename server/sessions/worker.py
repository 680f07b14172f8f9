"""The seam to the robot: what the robot daemon needs from the real-time worker (`WorkerControl`, which
`server.realtime.client.WorkerClient` implements), what web routes need from their robot (`RobotLink`,
which `server.robotd.link.DaemonLink` and `LocalLink` implement), and attaching a web process to its
robot's daemon, starting the daemon when none runs. Plain imports: an ImportError in the real-time
stack fails loudly instead of looking like "no robot"."""

from __future__ import annotations

import logging
import sys
from typing import Any, Protocol

import numpy as np

from server.robotd.estop import StopAnswer
from server.robotd.link import DaemonLink, ensure_daemon
from server.robotd.status import RobotPaths, RobotStatus
from server.settings import Settings

logger = logging.getLogger(__name__)
WEB_SWITCH_INTERVAL_S = 0.001


class WorkerControl(Protocol):
    """The WorkerClient interface (the part the robot daemon uses)."""

    def start(self) -> None: ...
    def shutdown(self) -> None: ...
    def load_prescription(
        self, prescription: dict[str, Any], patient: dict[str, Any] | None, estop_generation: int | None = None
    ) -> Any: ...
    def start_motion(self, estop_generation: int | None = None) -> Any: ...
    def estop_request(self) -> tuple[int, float | None]: ...
    def pause(self) -> Any: ...
    def resume(self) -> Any: ...
    def stop(self) -> Any: ...
    def emergency_stop(self) -> Any: ...
    def reset(self) -> Any: ...
    def latest_state(self) -> dict[str, Any]: ...
    def drain_telemetry(self) -> np.ndarray: ...
    def drain_events(self) -> list[dict[str, Any]]: ...


class RobotLink(Protocol):
    """What web routes use: commands to the daemon, and state read without asking it."""

    robot: str

    def open(self) -> None: ...
    def close(self) -> None: ...
    def emergency_stop(self) -> int | None: ...
    async def estop_confirmed(self, sequence: int | None) -> bool: ...
    def unconfirmed_stop(self) -> StopAnswer: ...
    def status(self, stale_s: float = ...) -> RobotStatus: ...
    def latest_state(self) -> dict[str, Any]: ...
    def frame(self) -> dict[str, Any]: ...
    def start_session(self, session_id: int, user_id: int) -> int: ...
    def control(self, session_id: int, command: Any, user_id: int, credential: str = ...) -> dict[str, Any] | None:
        """The run as the daemon knows it (`SessionRunOut`'s fields), once it decided; None when a stop
        cancelled the session's start while it was still loading."""

    def reset(self, user_id: int) -> None: ...
    def note_emergency_stop(self, user_id: int | None, authenticated: bool, credential: str) -> list[int]: ...
    def active_run(self) -> tuple[int, int] | None: ...
    def metrics_text(self) -> str: ...


DAEMON_SETTINGS = (
    "database_url",
    "backend",
    "robot_file",
    "control_rate_hz",
    "can_interface",
    "can_channel",
    "can_simulated_drives",
    "drive_communication_timeout_s",
    "log_flush_interval_s",
    "estop_host",
    "estop_port",
    "console_port",
    "realtime_cpu",
)


def daemon_environment(settings: Settings) -> dict[str, str]:
    """The settings a daemon started by this web process must share with it (command-line options
    included), as its environment."""
    environment = {}
    for name in DAEMON_SETTINGS:
        value = getattr(settings, name)
        if value is not None:
            environment[f"SSP_REHAB_{name.upper()}"] = str(value)
    return environment


def attach_robot(settings: Settings) -> DaemonLink:
    """This web process's link to the daemon of `settings.robot`; starts the daemon when none runs.
    Returns at once: the link reports "starting" or "absent" until the daemon is ready."""
    # Shorter GIL turns keep /estop and /health answering among busy request threads (a large upload).
    sys.setswitchinterval(min(sys.getswitchinterval(), WEB_SWITCH_INTERVAL_S))
    paths = RobotPaths(settings.data_dir.resolve(), settings.robot)
    environment = daemon_environment(settings)
    spawned = ensure_daemon(paths, environment)
    if spawned is not None:
        logger.info("started the robot daemon for %s (log: %s)", settings.robot, paths.log)
    link = DaemonLink(paths, restart_absent=True, environment=environment, spawned=spawned)
    link.open()
    return link
