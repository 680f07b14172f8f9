"""The web side's link to its robot: `DaemonLink` to a robot daemon process (the console's way), and
`LocalLink` to a `RobotDaemon` inside this process (tests with an in-memory worker); `attach_robot` links a
web process to its robot's daemon, starting the daemon when none runs.

A web process only sends commands and reads state. The emergency stop is a store into the worker's
control block in shared memory, with no lock, no wait and no message first; the answer then says
whether the worker saw it (it ticked after the store and shows the stop latched). Liveness is read,
not asked: the link socket's end (the daemon died), the status record's age (hung), its state.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

from server import messages as msg
from server.file_modes import private_directory
from server.realtime.shm import ControlBlock, Seqlock
from server.realtime.telemetry import TELEMETRY_DTYPE, state_dict
from server.robotd import estop
from server.robotd.daemon import VERIFIED_LOGIN, RobotDaemon
from server.robotd.estop import ESTOP_CONFIRM_TIMEOUT_S, StopAnswer
from server.robotd.runs import RunCommand
from server.robotd.status import (
    COMMAND_STALE_S,
    DAEMON_STALE_S,
    DaemonState,
    PidFile,
    RobotPaths,
    RobotStatus,
    StatusBlock,
    daemon_running,
    prioritise_liveness_thread,
)
from server.settings import Settings

log = logging.getLogger("ssp_rehab.robotd")

LINK_BEAT_PERIOD_S = 0.1
RECONNECT_PERIOD_S = 0.25
COMMAND_TIMEOUT_S = 900.0  # a start waits for the prescription check, which may take minutes
MAX_EVENTS_KEPT = 256
RESPAWN_PERIOD_S = 5.0
CONSOLE_ID_ENVIRONMENT = "SSP_REHAB_CONSOLE_ID"
DAEMON_LOCK_WAIT_S = 120.0  # a daemon's imports before it takes its lock, on a loaded machine
# Its controlled stop, the recorder's tail and the flush take seconds; a worker still compiling its kernels
# (a cold cache) lets the daemon end only once it has started.
DAEMON_STOP_TIMEOUT_S = 900.0
WEB_SWITCH_INTERVAL_S = 0.001
ANOTHER_CONSOLES_DAEMON = "the robot daemon is starting (started by another web process of this robot)"


class DaemonLink:
    """One web process's link to the daemon of `paths.robot` (started by `ensure_daemon` if need be)."""
    def __init__(
        self,
        paths: RobotPaths,
        *,
        restart_absent: bool = False,
        environment: dict[str, str] | None = None,
        spawned: subprocess.Popen[bytes] | None = None,
    ) -> None:
        self.paths = paths
        self.environment = environment or {}
        self._spawned = spawned  # the daemon this process started, while it may still be starting
        self._starting_reason = "the robot daemon is starting (loading)"
        self._linked_since_spawn = False
        self.robot = paths.robot
        self.restart_absent = restart_absent
        self._last_spawn_s = time.monotonic()
        self.link_id: str | None = None
        self._socket: socket.socket | None = None
        self._send_lock = threading.Lock()
        self._attach_lock = threading.Lock()
        self._status: StatusBlock | None = None
        self._control: ControlBlock | None = None
        self._state: Seqlock | None = None
        self.realtime: dict[str, Any] | None = None  # the worker's scheduling, as the daemon reports it
        self._events: collections.deque[dict[str, Any]] = collections.deque(maxlen=MAX_EVENTS_KEPT)
        self._closed = threading.Event()
        self._connected = threading.Event()
        self._thread = threading.Thread(target=self._keep_linked, name="robot-link", daemon=True)

    def open(self) -> None:
        self._thread.start()

    def wait_connected(self, timeout_s: float) -> bool:
        return self._connected.wait(timeout_s)

    # --- the emergency stop: first, and never behind anything -------------------------------------

    def emergency_stop(self) -> int | None:
        """Latch the stop in the worker's shared memory; the state sequence to confirm against, or None
        when there is no worker to receive it."""
        control, state = self._control, self._state
        if control is None or state is None:
            return None
        return estop.request_stop(control, state)

    async def estop_confirmed(self, sequence: int | None) -> bool:
        """True once the worker ticked after the store and shows the emergency stop latched. The last look
        comes after the deadline: a busy event loop that woke late still sees a latch that came in time."""
        state = self._state
        if sequence is None or state is None:
            return False
        deadline = time.monotonic() + ESTOP_CONFIRM_TIMEOUT_S
        while time.monotonic() < deadline:
            if estop.latched_after(state, sequence):
                return True
            await asyncio.sleep(estop.CONFIRM_POLL_S)
        return estop.latched_after(state, sequence)

    def unconfirmed_stop(self) -> StopAnswer:
        """The truthful answer for a stop the worker did not confirm: gone, not started, or slow."""
        why = f"robot {self.robot!r}: {self.status(COMMAND_STALE_S).reason}"
        return estop.unconfirmed(daemon_running(self.paths), self._control, why, ESTOP_CONFIRM_TIMEOUT_S)

    # --- state ---------------------------------------------------------------------------------------

    def status(self, stale_s: float = DAEMON_STALE_S) -> RobotStatus:
        """What /health shows; commands accept an older beat (`COMMAND_STALE_S`)."""
        if not self._connected.is_set() or self._status is None:
            spawned = self._spawned
            # Never "no robot" while the daemon this process started warms up (before its first link).
            if spawned is not None and not self._linked_since_spawn and spawned.poll() is None:
                return RobotStatus(DaemonState.STARTING, self._starting_reason, spawned.pid)
            # Not linked yet, but a daemon holds the robot's lock: another console's (several web processes
            # starting at once each spawn one; the lock admits one), still warming up.
            if not self._linked_since_spawn and daemon_running(self.paths):
                pid_file = PidFile.read(self.paths)
                pid = pid_file.pid if pid_file is not None else None
                return RobotStatus(DaemonState.STARTING, ANOTHER_CONSOLES_DAEMON, pid)
            return RobotStatus(DaemonState.ABSENT, "no robot daemon runs for this robot")
        return self._status.read(stale_s)

    def latest_state(self) -> dict[str, Any]:
        state = self._state
        if state is None:
            return {}
        return state_dict(state.read()[0])

    def frame(self) -> dict[str, Any]:
        """The parts of a telemetry frame: robot status, latest state and sample, events since the last frame."""
        status = self.status()
        state = self._state if status.ready else None
        events = []
        while self._events:
            events.append(self._events.popleft())
        record = state.read()[0] if state is not None else None
        return {
            "robot": status.to_dict(),
            "run_id": status.active_run_id,
            "session_id": status.active_session_id,
            "state": state_dict(record) if record is not None else None,
            "sample": {name: record[name] for name in TELEMETRY_DTYPE.names or ()} if record is not None else None,
            "events": events,
        }

    # --- commands --------------------------------------------------------------------------------------

    def start_session(self, session_id: int, user_id: int) -> int:
        # The emergency stops requested so far: one requested after this moment cancels the start.
        control = self._control
        generation = control.estop_request()[0] if control is not None else None
        run_id: int = self._request(
            msg.StartSession(
                session_id=session_id,
                user_id=user_id,
                link_id=self.link_id,
                estop_generation=generation,
                control_name=control.name if control is not None else None,
            )
        )
        return run_id

    def control(
        self, session_id: int, command: RunCommand, user_id: int, credential: str = VERIFIED_LOGIN
    ) -> dict[str, Any] | None:
        """The run as the daemon knows it once it decided (it never waits for the database); None when a stop
        cancelled the session's start while it was still loading."""
        run: dict[str, Any] | None = self._request(
            msg.ControlRun(session_id=session_id, command=command, user_id=user_id, credential=credential)
        )
        return run

    def reset(self, user_id: int) -> None:
        self._request(msg.ResetRobot(user_id=user_id))

    def note_emergency_stop(self, user_id: int | None, authenticated: bool, credential: str) -> list[int]:
        result: list[int] = self._request(
            msg.NoteEmergencyStop(user_id=user_id, authenticated=authenticated, credential=credential), timeout_s=10.0
        )
        return result

    def metrics_text(self) -> str:
        text: str = self._request(msg.Metrics(), timeout_s=2.0)
        return text

    def plan_status(self, session_id: int) -> dict[str, Any] | None:
        """The booking's plan state on this robot (`server.robotd.plans`); queues the plan if needed."""
        state: dict[str, Any] | None = self._request(msg.PlanStatus(session_id=session_id), timeout_s=5.0)
        return state

    def active_run(self) -> tuple[int, int] | None:
        status = self.status()
        if status.state is DaemonState.ABSENT:
            return None
        if status.active_run_id is None or status.active_session_id is None:
            return None
        return status.active_run_id, status.active_session_id

    def _request(self, request: msg.DaemonRequest, *, timeout_s: float = COMMAND_TIMEOUT_S) -> Any:
        from server.errors import WorkerUnavailableError

        status = self.status(COMMAND_STALE_S)
        if not status.ready:
            raise WorkerUnavailableError(f"robot {self.robot!r} is {status.state.label}: {status.reason}")
        try:
            return msg.exchange(str(self.paths.socket), request, timeout_s)
        except OSError as error:
            raise WorkerUnavailableError(f"robot {self.robot!r}: the robot daemon did not answer ({error})") from error
        except EOFError as error:
            raise WorkerUnavailableError(f"robot {self.robot!r}: {error}") from error

    # --- the link ----------------------------------------------------------------------------------------

    def _keep_linked(self) -> None:
        while not self._closed.is_set():
            try:
                self._link_once()
            except OSError:
                pass
            except Exception:
                log.exception("robot link failed")
            self._connected.clear()
            self._restart_if_absent()
            self._closed.wait(RECONNECT_PERIOD_S)

    def _restart_if_absent(self) -> None:
        """A daemon that died (kill -9, a crash) is started again, at most every RESPAWN_PERIOD_S: it
        closes the run it left open as interrupted, and the robot is free again."""

        if not self.restart_absent or time.monotonic() - self._last_spawn_s < RESPAWN_PERIOD_S:
            return
        if self._closed.is_set():
            return  # this web process is ending: its console may be stopping the daemon on purpose
        if self._spawned is not None and self._spawned.poll() is None:
            return  # still starting up (it takes the lock only once its imports are done)
        if not daemon_running(self.paths):
            log.warning("the robot daemon of %s is gone: starting it again", self.robot)
            code = self._spawned.poll() if self._spawned is not None else None
            ended = f"the robot daemon ended (exit code {code})" if code is not None else "the robot daemon ended"
            self._starting_reason = f"{ended}: the drives stop on their own heartbeat loss; starting it again"
            self._last_spawn_s = time.monotonic()
            self._linked_since_spawn = False
            self._spawned = spawn_daemon(self.paths, self.environment)

    def _link_once(self) -> None:
        connection = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            connection.connect(str(self.paths.socket))
            hello = msg.Hello(persistent=True, web_pid=os.getpid(), console=console_id())
            connection.sendall(msg.encode_line(hello))
            reader = connection.makefile("rb")
            line = reader.readline()
            if not line:
                return
            try:
                names: msg.DaemonNames = msg.decode_reply(line, hello)
            except Exception as error:
                log.warning("the robot daemon refused the link: %s", error)
                return
            self._attach(names)
            self.link_id = names.link_id
            self._socket = connection
            self._linked_since_spawn = True
            self._connected.set()
            beating = threading.Thread(target=self._beat, args=(connection,), name="robot-link-beat", daemon=True)
            beating.start()
            for line in reader:  # until the daemon's end closes the socket
                match msg.decode_push(line):
                    case msg.EventsPush(events=events):
                        self._events.extend(events)
                    case msg.ReadyPush(names=names):
                        self._attach(names)
        finally:
            self._connected.clear()
            self._socket = None
            with contextlib.suppress(OSError):
                connection.close()

    def _attach(self, names: msg.DaemonNames) -> None:
        with self._attach_lock:
            if names.realtime is not None:
                self.realtime = names.realtime
            if names.status_name and (self._status is None or self._status.name != names.status_name):
                self._status = StatusBlock(names.status_name)
            if names.control_name and (self._control is None or self._control.name != names.control_name):
                self._control = ControlBlock(names.control_name)
                self._state = Seqlock(TELEMETRY_DTYPE, names.state_name)

    def _beat(self, connection: socket.socket) -> None:
        prioritise_liveness_thread("the robot link's beat")
        while self._socket is connection and not self._closed.is_set():
            try:
                with self._send_lock:
                    connection.sendall(b"b\n")
            except OSError:
                return
            time.sleep(LINK_BEAT_PERIOD_S)

    def close(self) -> None:
        self._closed.set()
        connection = self._socket
        if connection is not None:
            with contextlib.suppress(OSError):
                connection.shutdown(socket.SHUT_RDWR)
        self._thread.join(2.0)
        self._settle_spawned()

    def _settle_spawned(self) -> None:
        """A daemon this process started that has not taken the robot's lock yet (still importing) is waited
        for until it takes it or exits: the console that started it then finds it, to stop it or leave it."""
        spawned = self._spawned
        deadline = time.monotonic() + DAEMON_LOCK_WAIT_S
        while spawned is not None and spawned.poll() is None and time.monotonic() < deadline:
            if daemon_running(self.paths) and PidFile.read(self.paths) is not None:
                return
            time.sleep(0.05)


class LocalLink:
    """The same interface to a `RobotDaemon` in this process (tests: an in-memory worker, a test database)."""
    def __init__(self, daemon: RobotDaemon) -> None:
        self.daemon = daemon
        self.robot = daemon.robot
        self._events: collections.deque[dict[str, Any]] = collections.deque(maxlen=MAX_EVENTS_KEPT)
        daemon.listeners.append(self._events.extend)

    def open(self) -> None:
        self.daemon.start()

    def emergency_stop(self) -> int | None:
        self.daemon.worker.emergency_stop()
        return 0

    async def estop_confirmed(self, sequence: int | None) -> bool:
        return sequence is not None

    def unconfirmed_stop(self) -> StopAnswer:
        return estop.unconfirmed(True, None, "in-process robot", ESTOP_CONFIRM_TIMEOUT_S)

    def status(self, stale_s: float = DAEMON_STALE_S) -> RobotStatus:
        run = self.daemon.active_run()
        run_id, session_id = run or (None, None)
        failure = self.daemon.recorder.failure
        return RobotStatus(DaemonState.READY, "in-process robot", os.getpid(), run_id, session_id, failure)

    def latest_state(self) -> dict[str, Any]:
        return self.daemon.worker.latest_state()

    def frame(self) -> dict[str, Any]:
        status = self.status()
        events = []
        while self._events:
            events.append(self._events.popleft())
        recent = self.daemon.run
        return {
            "robot": status.to_dict(),
            "run_id": recent.run_id if recent is not None else None,
            "session_id": recent.session_id if recent is not None else None,
            "state": self.latest_state(),
            "sample": self.daemon.latest_sample,
            "events": events,
        }

    def start_session(self, session_id: int, user_id: int) -> int:
        return self.daemon.start_session(session_id, user_id)

    def control(
        self, session_id: int, command: RunCommand, user_id: int, credential: str = VERIFIED_LOGIN
    ) -> dict[str, Any] | None:
        return self.daemon.control(session_id, command, user_id, credential)

    def reset(self, user_id: int) -> None:
        self.daemon.reset(user_id)

    def note_emergency_stop(self, user_id: int | None, authenticated: bool, credential: str) -> list[int]:
        return self.daemon.note_emergency_stop(user_id, authenticated, credential)

    def metrics_text(self) -> str:
        return self.daemon.metrics_text()

    def plan_status(self, session_id: int) -> dict[str, Any] | None:
        return self.daemon.plans.status(session_id)

    def active_run(self) -> tuple[int, int] | None:
        return self.daemon.active_run()

    def close(self) -> None:
        self.daemon.shutdown()


def console_id() -> str:
    """The console this web process serves: `serve --workers N` gives its processes one id
    (`SSP_REHAB_CONSOLE_ID`), so that they share the session-control lease; otherwise the process's own."""
    return os.environ.get(CONSOLE_ID_ENVIRONMENT) or f"process-{os.getpid()}"


def spawn_daemon(paths: RobotPaths, environment: dict[str, str] | None = None) -> subprocess.Popen[bytes]:
    """`ssp-rehab robot --robot NAME` in its own session, so that it outlives this web process; it names
    this process's console as the one that started it (`stop_started_daemon`)."""
    private_directory(paths.directory)
    with paths.log.open("ab") as log_file:
        return subprocess.Popen(
            [
                sys.executable,
                "-m",
                "server.cli.main",
                "robot",
                "--robot",
                paths.robot,
                "--data-dir",
                str(paths.data_dir),
                "--started-by",
                console_id(),
            ],
            env={**os.environ, **(environment or {})},
            stdin=subprocess.DEVNULL,
            stdout=log_file,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def ensure_daemon(paths: RobotPaths, environment: dict[str, str] | None = None) -> subprocess.Popen[bytes] | None:
    """Start the robot's daemon unless one runs; the process if this call started it."""
    if daemon_running(paths):
        return None
    return spawn_daemon(paths, environment)


@dataclass(frozen=True)
class DaemonEnd:
    ended: bool  # it ended, and released the robot's lock, before the timeout
    clean: bool  # through its own shutdown (a run in motion stopped under control, records flushed)


def running_daemon(paths: RobotPaths) -> PidFile | None:
    """The pid file of the daemon holding the robot's lock, or None when none holds it. A daemon writes its
    pid file just after taking the lock: that moment is waited out."""

    deadline = time.monotonic() + DAEMON_LOCK_WAIT_S
    while daemon_running(paths):
        pid_file = PidFile.read(paths)
        if pid_file is not None and _alive(pid_file.pid):
            return pid_file
        if time.monotonic() > deadline:
            return None
        time.sleep(0.05)
    return None


def stop_daemon(paths: RobotPaths, daemon: PidFile, timeout_s: float = DAEMON_STOP_TIMEOUT_S) -> DaemonEnd:
    """SIGTERM, as systemd stops it: its shutdown interrupts a run in motion with a controlled stop and
    flushes the records, then it removes its pid file and releases the lock. Waits for that."""

    with contextlib.suppress(ProcessLookupError):
        os.kill(daemon.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout_s
    while (daemon_running(paths) or _alive(daemon.pid)) and time.monotonic() < deadline:
        time.sleep(0.05)
    ended = not daemon_running(paths) and not _alive(daemon.pid)
    left = PidFile.read(paths)  # a daemon that ended without its shutdown leaves its pid file
    return DaemonEnd(ended, ended and (left is None or left.pid != daemon.pid))


def _alive(pid: int) -> bool:
    """True while `pid` runs (a zombie, dead but not yet reaped by its parent, does not count)."""
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] not in ("Z", "X")
    except (OSError, IndexError):
        return False


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
    "plan_store_max_mb",
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
        log.info("started the robot daemon for %s (log: %s)", settings.robot, paths.log)
    link = DaemonLink(paths, restart_absent=True, environment=environment, spawned=spawned)
    link.open()
    return link
