"""The robot daemon process (`ssp-rehab robot --robot NAME`): one per robot, found through its lock file.

It holds an exclusive `flock` on `robots/NAME.lock` for its lifetime (a second daemon for the same robot
refuses to start), writes `robots/NAME.pid`, publishes its status record in shared memory every 20 ms,
and serves web processes on the Unix socket `robots/NAME.sock` with one JSON object per line:

- `{"cmd": "hello", "persistent": true}` opens a console's link: the answer names the shared-memory
  blocks (status, control flags, latest state); the link then carries `beat`s from the console and
  pushes events to it. The daemon watches the link: its end (the console process died) or 1 s of
  silence stops a run that console started;
- `start`, `control`, `reset`, `estop_note`, `active_run`: one request and one answer each.

Start-up order: status "starting" at once, then recovery of runs a crash left open, then the worker
(its kernels compile here), the planning process and the recorder; then "ready".
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import signal
import socket
import socketserver
import threading
import time
import uuid
from pathlib import Path
from typing import Any

from server.db import Database, create_database_engine, upgrade_database
from server.realtime.client import WorkerClient
from server.robotd.daemon import RobotDaemon, refusal_to_dict
from server.robotd.planner import Planner
from server.robotd.recovery import recover_open_runs
from server.robotd.status import (
    STATUS_PERIOD_S,
    DaemonState,
    RobotPaths,
    StatusBlock,
    prioritise_liveness_thread,
)
from server.settings import Settings

log = logging.getLogger("ssp_rehab.robotd")
WORKER_STALL_S = 1.0  # the worker's state stopped advancing this long: hung (idle collections take ~0.3 s loaded)
WORKER_START_TIMEOUT_S = 1800.0  # a cold numba cache on a loaded machine compiles for many minutes


class AlreadyRunning(RuntimeError):  # noqa: N818 — a state, not a malfunction
    pass


def hal_options(settings: Settings) -> dict[str, Any]:
    if settings.backend == "canopen":
        return {
            "interface": settings.can_interface,
            "channel": settings.can_channel,
            "simulate": settings.can_simulated_drives,
        }
    if settings.drive_communication_timeout_s is not None:
        return {"communication_timeout_s": settings.drive_communication_timeout_s}
    return {}


def take_lock(paths: RobotPaths) -> int:
    """The robot's lock (held until this process ends, however it ends), or `AlreadyRunning`."""
    paths.directory.mkdir(parents=True, exist_ok=True)
    descriptor = os.open(paths.lock, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(descriptor)
        owner = paths.pid.read_text().strip() if paths.pid.exists() else "unknown"
        raise AlreadyRunning(f"a robot daemon for {paths.robot!r} is already running (pid {owner})") from None
    return descriptor


def daemon_running(paths: RobotPaths) -> bool:
    """True while some process holds the robot's lock."""
    if not paths.lock.exists():
        return False
    descriptor = os.open(paths.lock, os.O_RDWR)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(descriptor)  # closing drops a lock taken here
    return False


class RobotDaemonProcess:
    def __init__(self, settings: Settings, robot: str) -> None:
        self.settings = settings
        self.paths = RobotPaths(settings.data_dir.resolve(), robot)
        self.state, self.reason = DaemonState.STARTING, "starting: recovering open runs"
        self.status: StatusBlock | None = None  # created once the lock is ours
        self.worker: WorkerClient | None = None
        self.planner: Planner | None = None
        self.daemon: RobotDaemon | None = None
        self.links: dict[str, socket.socket] = {}
        self.link_pids: dict[str, int | None] = {}
        self._links_lock = threading.Lock()
        self._stop = threading.Event()
        self._worker_lost = False
        self._started_s = time.monotonic()

    # --- status ---------------------------------------------------------------------------------

    def set_state(self, state: DaemonState, reason: str) -> None:
        self.state, self.reason = state, reason
        log.info("robot %s: %s (%s)", self.paths.robot, state.label, reason)
        self._publish()

    def _publish(self) -> None:
        run = self.daemon.active_run() if self.daemon is not None else None
        if self.status is None:
            return
        reason = self.reason
        if self.state is DaemonState.STARTING:  # progress while it warms up: the step and how long so far
            reason = f"{reason} ({time.monotonic() - self._started_s:.0f} s so far)"
        self.status.publish(self.state, reason, os.getpid(), run)

    def _beat_forever(self) -> None:
        prioritise_liveness_thread("the daemon's status beat")
        last_sequence, last_change = -1, time.monotonic()
        while not self._stop.wait(STATUS_PERIOD_S):
            worker = self.worker
            if (
                worker is not None
                and worker.process is not None
                and self.state in (DaemonState.READY, DaemonState.FAULT)
                and not self._worker_lost
            ):
                if not worker.process.is_alive():
                    self._lose_worker(f"the real-time worker exited (exit code {worker.process.exitcode})")
                else:
                    sequence, now = worker.state.sequence, time.monotonic()
                    if sequence != last_sequence:
                        last_sequence, last_change = sequence, now
                        if self.state is DaemonState.FAULT:
                            self.set_state(DaemonState.READY, "the real-time worker runs again")
                    elif now - last_change > WORKER_STALL_S and self.state is DaemonState.READY:
                        self.set_state(DaemonState.FAULT, "the real-time worker stopped ticking (hung or stopped)")
            self._publish()

    def _lose_worker(self, what: str) -> None:
        self._worker_lost = True
        reason = f"{what}: the drives stopped on their own heartbeat loss; restart the robot daemon"
        self.set_state(DaemonState.FAULT, reason)
        if self.daemon is not None:
            self.daemon.worker_lost(reason)

    # --- the socket -------------------------------------------------------------------------------

    def hello(self) -> dict[str, Any]:
        worker = self.worker if self.state is not DaemonState.STARTING else None
        return {
            "robot": self.paths.robot,
            "pid": os.getpid(),
            "status_name": self.status.name if self.status is not None else None,
            "control_name": worker.control.name if worker is not None else None,
            "state_name": worker.state.name if worker is not None else None,
        }

    def push(self, message: dict[str, Any]) -> None:
        """To every console link; never blocks (a console that does not read loses pushes, not the daemon)."""
        data = (json.dumps(message) + "\n").encode()
        with self._links_lock:
            links = list(self.links.values())
        for link in links:
            with contextlib.suppress(OSError):
                link.send(data, socket.MSG_DONTWAIT)

    def handle(self, request: dict[str, Any]) -> Any:
        command = request.get("cmd")
        if command == "hello":
            return self.hello()
        daemon = self.daemon
        if daemon is None:
            from server.errors import WorkerUnavailableError

            raise WorkerUnavailableError(f"robot {self.paths.robot!r} is {self.state.label}: {self.reason}")
        if command == "start":
            # The emergency-stop count the console read when the start was asked for, if read from this worker.
            worker = self.worker
            same_worker = worker is not None and request.get("control_name") == worker.control.name
            generation = request.get("estop_generation") if same_worker else None
            return daemon.start_session(
                int(request["session_id"]),
                int(request["user_id"]),
                request.get("link_id"),
                int(generation) if generation is not None else None,
            )
        if command == "control":
            return daemon.control(int(request["session_id"]), request["command"], int(request["user_id"]))
        if command == "reset":
            daemon.reset(int(request["user_id"]))
            return None
        if command == "estop_note":
            return daemon.note_emergency_stop(
                request.get("user_id"), bool(request["authenticated"]), request["credential"]
            )
        if command == "active_run":
            return daemon.active_run()
        if command == "metrics":
            return daemon.metrics_text()
        raise ValueError(f"cmd = {command!r}: unknown")

    def serve_link(self, connection: socket.socket, reader: Any, web_pid: int | None) -> None:
        prioritise_liveness_thread("a console link")  # its beats decide whether the console is alive
        link_id = uuid.uuid4().hex
        with self._links_lock:
            self.links[link_id] = connection
            self.link_pids[link_id] = web_pid
        if self.daemon is not None:
            self.daemon.link_opened(link_id, web_pid)
        try:
            _send(connection, {"ok": True, "result": {**self.hello(), "link_id": link_id}})
            for line in reader:
                if self.daemon is not None and line.strip():
                    self.daemon.link_beat(link_id)
        except OSError:
            pass
        finally:
            with self._links_lock:
                self.links.pop(link_id, None)
                self.link_pids.pop(link_id, None)
            if self.daemon is not None:
                self.daemon.link_closed(link_id)

    # --- lifecycle ----------------------------------------------------------------------------------

    def run(self) -> int:
        lock = take_lock(self.paths)
        self.paths.pid.write_text(f"{os.getpid()}\n")
        _unlink_stale_shared_memory(self.paths)
        self.status = status = StatusBlock()
        self.paths.shared_memory.write_text(status.name + "\n")
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, lambda *_: self._stop.set())
        self._publish()
        beats = threading.Thread(target=self._beat_forever, name="robotd-status", daemon=True)
        beats.start()
        server = _serve_socket(self)
        engine = None
        try:
            engine = create_database_engine(self.settings.resolved_database_url())
            upgrade_database(engine)
            database = Database(engine)
            closed = recover_open_runs(database=database, robot=self.paths.robot, journal_dir=self.paths.journal)
            if closed:
                log.warning("closed runs left open by a crash as interrupted: %s", closed)
            self.set_state(DaemonState.STARTING, "starting: compiling the real-time kernels and starting the worker")
            settings = self.settings
            self.worker = WorkerClient(
                str(settings.robot_file) if settings.robot_file else None,
                settings.backend,
                settings.control_rate_hz,
                hal_options=hal_options(settings),
            )
            self.worker.start(timeout_s=WORKER_START_TIMEOUT_S)
            worker_blocks = (self.worker.control, self.worker.state, self.worker.telemetry, self.worker.events)
            names = [status.name, *(block.name for block in worker_blocks)]
            self.paths.shared_memory.write_text("\n".join(names) + "\n")
            self.planner = Planner(self.worker.twin_path, settings.control_rate_hz, self.worker.supervisor_config)
            self.planner.start()
            self.daemon = RobotDaemon(
                robot=self.paths.robot,
                worker=self.worker,
                database=database,
                journal_dir=self.paths.journal,
                planner=self.planner,
                chunk_period_s=settings.log_flush_interval_s,
            )
            self.daemon.listeners.append(lambda events: self.push({"push": "events", "events": events}))
            with self._links_lock:
                for link_id, web_pid in self.link_pids.items():
                    self.daemon.link_opened(link_id, web_pid)
            self.daemon.start()
            self.set_state(DaemonState.READY, f"backend {settings.backend} at {settings.control_rate_hz} Hz")
            self.push({"push": "ready", **self.hello()})
            self._stop.wait()
            self.set_state(DaemonState.STOPPING, "shutting down")
            return 0
        except Exception as error:
            log.exception("the robot daemon failed")
            self.set_state(DaemonState.FAULT, f"{type(error).__name__}: {error}"[:200])
            self._stop.wait(2.0)  # long enough for attached consoles to read why
            return 1
        finally:
            if self.daemon is not None:
                self.daemon.shutdown()
            if self.worker is not None and self.worker.process is not None:
                self.worker.shutdown()
            if self.planner is not None:
                self.planner.shutdown()
            self._stop.set()
            server.shutdown()
            server.server_close()
            with contextlib.suppress(FileNotFoundError):
                self.paths.socket.unlink()
            with contextlib.suppress(FileNotFoundError):
                self.paths.pid.unlink()
            with contextlib.suppress(FileNotFoundError):
                self.paths.shared_memory.unlink()
            beats.join(1.0)
            status.close()
            if engine is not None:
                engine.dispose()
            os.close(lock)


def _unlink_stale_shared_memory(paths: RobotPaths) -> None:
    """A crashed daemon could not free its blocks; they are only names now (any mapping stays valid)."""
    if not paths.shared_memory.exists():
        return
    for name in paths.shared_memory.read_text().split():
        with contextlib.suppress(OSError):
            os.unlink(f"/dev/shm/{name.lstrip('/')}")
    paths.shared_memory.unlink()


def _send(connection: socket.socket, message: dict[str, Any]) -> None:
    connection.sendall((json.dumps(message, default=str) + "\n").encode())


def _serve_socket(owner: RobotDaemonProcess) -> socketserver.UnixStreamServer:
    class Handler(socketserver.StreamRequestHandler):
        def handle(self) -> None:
            line = self.rfile.readline()
            if not line:
                return
            try:
                request = json.loads(line)
            except ValueError:
                return
            if request.get("cmd") == "hello" and request.get("persistent"):
                owner.serve_link(self.connection, self.rfile, request.get("web_pid"))
                return
            try:
                reply = {"ok": True, "result": owner.handle(request)}
            except Exception as error:
                if not isinstance(error, (LookupError, RuntimeError, ValueError)):
                    log.exception("robot daemon command %r failed", request.get("cmd"))
                reply = {"ok": False, "error": refusal_to_dict(error)}
            with contextlib.suppress(OSError):
                _send(self.connection, reply)

    class Server(socketserver.ThreadingMixIn, socketserver.UnixStreamServer):
        daemon_threads = True

    path: Path = owner.paths.socket
    with contextlib.suppress(FileNotFoundError):
        path.unlink()  # a stale socket of a crashed daemon: the lock says it is ours now
    server = Server(str(path), Handler)
    os.chmod(path, 0o600)
    threading.Thread(
        target=server.serve_forever, kwargs={"poll_interval": 0.2}, name="robotd-socket", daemon=True
    ).start()
    return server


def run_robot_daemon(settings: Settings, robot: str) -> int:
    """Process entry (`ssp-rehab robot`): the exit code."""
    return RobotDaemonProcess(settings, robot).run()
