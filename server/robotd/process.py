"""The robot daemon process (`ssp-rehab robot --robot NAME`): one per robot, found through its lock file.

It holds an exclusive `flock` on `robots/NAME.lock` for its lifetime (a second daemon for the same robot
refuses to start), writes `robots/NAME.pid`, publishes its status record in shared memory every 20 ms,
and serves web processes on the Unix socket `robots/NAME.sock` with one typed message (server.messages) a line:

- `Hello(persistent=True)` opens a console's link: the answer names the shared-memory
  blocks (status, control flags, latest state); the link then carries `beat`s from the console and
  pushes events to it. The daemon watches the link: its end (the console process died) or 1 s of
  silence stops a run that console started;
- every other request (start, control, reset, …) has one answer, a `DaemonReply`.

Beside it runs its emergency-stop listener (`server.robotd.estop_listener`), a child process that ends with it.

Start-up order: status "starting" at once, then recovery of runs a crash left open, then the worker
(its kernels compile here), the planning process and the recorder; then "ready".

A worker that dies is started again here (drives off, its predecessor's stop latched as a `worker_lost`
fault for a therapist to reset), at most once per `WORKER_RESTART_MIN_INTERVAL_S`. A daemon that dies
is started again by the web side's link (server.robotd.link); the robot's lock admits one daemon. If
that daemon's recovery closed a run, its fresh worker latches a `daemon_lost` fault the same way.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
import signal
import socket
import socketserver
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from typing import Any

import msgspec

from core.robot import default_twin, load_twin
from server import messages as msg
from server.db import Database, create_database_engine, upgrade_database
from server.errors import InvalidFieldError
from server.file_modes import private_directory
from server.realtime.client import WorkerClient
from server.realtime.scheduling import RealtimeReport, parse_cpu_request
from server.robotd.daemon import DAEMON_STOPPED, RobotDaemon
from server.robotd.plan_store import PlanStore
from server.robotd.planner import Planner
from server.robotd.recovery import recover_open_runs
from server.robotd.status import (
    STATUS_PERIOD_S,
    DaemonState,
    PidFile,
    RobotPaths,
    StatusBlock,
    prioritise_liveness_thread,
)
from server.settings import Settings

log = logging.getLogger("ssp_rehab.robotd")
WORKER_STALL_S = 1.0  # the worker's state stopped advancing this long: hung (idle collections take ~0.3 s loaded)
WORKER_START_TIMEOUT_S = 1800.0  # a cold numba cache on a loaded machine compiles for many minutes
WORKER_RESTART_MIN_INTERVAL_S = 60.0  # a worker that dies again this soon is not restarted (a crash loop)


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
    private_directory(paths.directory)
    descriptor = os.open(paths.lock, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(descriptor)
        pid_file = PidFile.read(paths)
        owner = pid_file.pid if pid_file is not None else "unknown"
        raise AlreadyRunning(f"a robot daemon for {paths.robot!r} is already running (pid {owner})") from None
    return descriptor


class RobotDaemonProcess:
    def __init__(self, settings: Settings, robot: str, started_by: str | None = None) -> None:
        self.settings = settings
        self.started_by = started_by  # the console (`serve`) that started this daemon and stops it on its exit
        self.paths = RobotPaths(settings.data_dir.resolve(), robot)
        self.state, self.reason = DaemonState.STARTING, "starting: recovering open runs"
        self.status: StatusBlock | None = None  # created once the lock is ours
        self.worker: WorkerClient | None = None
        self.planner: Planner | None = None
        self.daemon: RobotDaemon | None = None
        self.links: dict[str, socket.socket] = {}
        self.link_pids: dict[str, int | None] = {}
        self.link_consoles: dict[str, str | None] = {}  # the console (`serve`) each link's web process serves
        self._links_lock = threading.Lock()
        self._stop = threading.Event()
        self._stopped_by: str | None = None  # the signal that asked this daemon to end
        self._worker_lost = False
        self._worker_restarted_s: float | None = None  # the last restart of a dead worker
        self._restarting: threading.Thread | None = None  # the thread starting a new worker, if any
        self._started_s = time.monotonic()
        self.database: Database | None = None
        self.estop_listener: subprocess.Popen[bytes] | None = None

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
        recording_failure = self.daemon.recorder.failure if self.daemon is not None else None
        self.status.publish(self.state, reason, os.getpid(), run, recording_failure)

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
                    self._lose_worker(worker)
                else:
                    sequence, now = worker.state.sequence, time.monotonic()
                    if sequence != last_sequence:
                        last_sequence, last_change = sequence, now
                        if self.state is DaemonState.FAULT:
                            self.set_state(DaemonState.READY, "the real-time worker runs again")
                    elif now - last_change > WORKER_STALL_S and self.state is DaemonState.READY:
                        self.set_state(DaemonState.FAULT, "the real-time worker stopped ticking (hung or stopped)")
            self._publish()

    def _lose_worker(self, worker: WorkerClient) -> None:
        """The worker died: record the stop on the run, then start a new worker (in its own thread: the
        status beat goes on meanwhile)."""
        self._worker_lost = True
        assert worker.process is not None
        code = worker.process.exitcode
        killed_by = signal.Signals(-code).name if code is not None and code < 0 else None
        what = f"killed by {killed_by}" if killed_by else f"exit code {code}"
        details = {"pid": worker.process.pid, "exit_code": code, "signal": killed_by,
                   "last_tick": int(worker.state.read()[0]["tick"])}  # fmt: skip
        reason = f"the real-time worker died ({what}): the drives stopped on their own heartbeat loss"
        restart = self._worker_restarted_s is None or (
            time.monotonic() - self._worker_restarted_s >= WORKER_RESTART_MIN_INTERVAL_S
        )
        self.set_state(
            DaemonState.FAULT if not restart else DaemonState.STARTING,
            f"{reason}; " + ("starting a new worker (drives off)" if restart else
                             f"it died again within {WORKER_RESTART_MIN_INTERVAL_S:g} s: restart the robot daemon"),
        )  # fmt: skip
        if self.daemon is not None:
            self.daemon.worker_lost(reason, details)
        if restart:
            self._restarting = threading.Thread(
                target=self._restart_worker, args=(worker, details), name="robotd-worker-restart", daemon=True
            )
            self._restarting.start()

    def _new_worker(self) -> WorkerClient:
        settings = self.settings
        worker = WorkerClient(
            str(settings.robot_file) if settings.robot_file else None,
            settings.backend,
            settings.control_rate_hz,
            cpu=parse_cpu_request(settings.realtime_cpu),
            hal_options=hal_options(settings),
        )
        worker.start(timeout_s=WORKER_START_TIMEOUT_S)
        self._announce_realtime(worker)
        return worker

    def _name_shared_memory(self, worker: WorkerClient) -> None:
        assert self.status is not None
        blocks = (worker.control, worker.state, worker.telemetry, worker.events)
        self.paths.shared_memory.write_text("\n".join([self.status.name, *(b.name for b in blocks)]) + "\n")

    def _restart_worker(self, dead: WorkerClient, details: dict[str, Any]) -> None:
        self._worker_restarted_s = time.monotonic()
        try:
            worker = self._new_worker()
            worker.latch_fault("worker_lost", details)  # shown until a therapist resets; drives stay off
        except Exception as error:
            log.exception("could not start a new real-time worker")
            self.set_state(DaemonState.FAULT, f"could not start a new real-time worker ({error}); restart the daemon")
            return
        if self.daemon is not None:
            self.daemon.replace_worker(worker)
        self.worker = worker
        try:
            dead.shutdown(timeout_s=5.0)  # its heartbeat relay and shared memory go with it
        except Exception:
            log.exception("the dead worker's relay or shared memory could not be freed")
        self._name_shared_memory(worker)
        self._worker_lost = False
        self.set_state(DaemonState.READY, "a new real-time worker runs (drives off): reset the robot")
        self.push(msg.ReadyPush(names=self.hello()))

    def realtime(self, worker: WorkerClient | None = None) -> dict[str, Any] | None:
        """The worker's scheduling as /health shows it (None until the worker runs)."""
        worker = worker or self.worker
        setup = getattr(worker, "realtime_setup", None) if worker is not None else None
        return RealtimeReport.from_setup(setup).to_dict() if setup else None

    def _announce_realtime(self, worker: WorkerClient) -> None:
        report = self.realtime(worker)
        if report is None:
            return
        if report["granted"]:
            log.info("real-time worker: SCHED_FIFO %s on CPU %s of its own", report["priority"], report["cpu"])
        else:
            log.warning(
                "real-time scheduling NOT granted (%s): sessions may stop on late ticks on a busy computer. %s",
                "; ".join(report["refusals"]),
                report["how_to_fix"],
            )

    # --- the socket -------------------------------------------------------------------------------

    def hello(self, link_id: str | None = None) -> msg.DaemonNames:
        worker = self.worker if self.state is not DaemonState.STARTING else None
        return msg.DaemonNames(
            robot=self.paths.robot,
            pid=os.getpid(),
            status_name=self.status.name if self.status is not None else None,
            control_name=worker.control.name if worker is not None else None,
            state_name=worker.state.name if worker is not None else None,
            realtime=self.realtime(),
            link_id=link_id,
        )

    def push(self, message: msg.DaemonPush) -> None:
        """To every console link; never blocks (a console that does not read loses pushes, not the daemon)."""
        data = msg.encode_line(message)
        with self._links_lock:
            links = list(self.links.values())
        for link in links:
            with contextlib.suppress(OSError):
                link.send(data, socket.MSG_DONTWAIT)

    def handle(self, request: msg.DaemonRequest) -> Any:
        if isinstance(request, msg.Hello):
            return self.hello()
        daemon = self.daemon
        if daemon is None:
            from server.errors import WorkerUnavailableError

            raise WorkerUnavailableError(f"robot {self.paths.robot!r} is {self.state.label}: {self.reason}")
        match request:
            case msg.StartSession():
                # The emergency-stop count the console read when the start was asked for, if read from this worker.
                worker = self.worker
                same_worker = worker is not None and request.control_name == worker.control.name
                generation = request.estop_generation if same_worker else None
                return daemon.start_session(request.session_id, request.user_id, request.link_id, generation)
            case msg.ControlRun():
                return daemon.control(request.session_id, request.command, request.user_id, request.credential)
            case msg.ResetRobot():
                daemon.reset(request.user_id)
                return None
            case msg.NoteEmergencyStop():
                return daemon.note_emergency_stop(request.user_id, request.authenticated, request.credential)
            case msg.AuditListenerStop():  # from the stop listener, after its answer: who asked, checked here
                return self.audit_listener_stop(request.token, request.outcome)
            case msg.ActiveRun():
                return daemon.active_run()
            case msg.PlanStatus():
                return daemon.plans.status(request.session_id)
            case msg.Metrics():
                return daemon.metrics_text()
        raise ValueError(f"request = {request!r}: unknown")

    def audit_listener_stop(self, token: str | None, outcome: str) -> list[int]:
        """The stop listener's stop: who asked (the token it carried, checked as the web side checks it)."""
        from server.auth.dependencies import credential_of
        from server.auth.security import TokenSigner

        assert self.daemon is not None and self.database is not None
        claims = TokenSigner(self.settings.resolved_secret_key()).verify(token) if token else None
        user_id, credential = credential_of(self.database, claims, token is not None)
        if outcome != "confirmed":
            credential += f"; not confirmed by the worker in time ({outcome})"
        return self.daemon.note_emergency_stop(user_id, user_id is not None, f"{credential}; via the stop listener")

    def serve_link(
        self, connection: socket.socket, reader: Any, web_pid: int | None, console: str | None = None
    ) -> None:
        prioritise_liveness_thread("a console link")  # its beats decide whether the console is alive
        link_id = uuid.uuid4().hex
        with self._links_lock:
            self.links[link_id] = connection
            self.link_pids[link_id] = web_pid
            self.link_consoles[link_id] = console
        if self.daemon is not None:
            self.daemon.link_opened(link_id, web_pid, console)
        try:
            connection.sendall(msg.encode_line(msg.DaemonReply(result=self.hello(link_id))))
            for line in reader:
                if self.daemon is not None and line.strip():
                    self.daemon.link_beat(link_id)
        except OSError:
            pass
        finally:
            with self._links_lock:
                self.links.pop(link_id, None)
                self.link_pids.pop(link_id, None)
                self.link_consoles.pop(link_id, None)
            if self.daemon is not None:
                self.daemon.link_closed(link_id)

    # --- lifecycle ----------------------------------------------------------------------------------

    def _on_stop_signal(self, signum: int, _frame: Any) -> None:
        self._stopped_by = self._stopped_by or signal.Signals(signum).name
        self._stop.set()

    def run(self) -> int:
        lock = take_lock(self.paths)
        left = PidFile.read(self.paths)  # a clean end removes it: one left behind is a crashed daemon's
        previous_pid = left.pid if left is not None else None
        self.paths.pid.write_text(PidFile(os.getpid(), self.started_by).text())
        _unlink_stale_shared_memory(self.paths)
        self.status = status = StatusBlock()
        self.paths.shared_memory.write_text(status.name + "\n")
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, self._on_stop_signal)
        self._publish()
        beats = threading.Thread(target=self._beat_forever, name="robotd-status", daemon=True)
        beats.start()
        server = _serve_socket(self)
        engine = None
        try:
            # Started first: its start-up overlaps the worker's; it attaches the worker's blocks once listed.
            self.estop_listener = start_estop_listener(self.paths)
            engine = create_database_engine(self.settings.resolved_database_url())
            upgrade_database(engine)
            self.database = database = Database(engine)
            closed = recover_open_runs(
                database=database,
                robot=self.paths.robot,
                journal_dir=self.paths.journal,
                lost_daemon_pid=previous_pid,
            )
            if closed:
                log.warning("closed runs left open by a crash as interrupted: %s", closed)
            self.set_state(DaemonState.STARTING, "starting: compiling the real-time kernels and starting the worker")
            settings = self.settings
            self.worker = self._new_worker()
            if closed:  # the daemon before this one died during a run: a therapist resets before the next
                self.worker.latch_fault("daemon_lost", {"pid": previous_pid, "runs": closed})
            self._name_shared_memory(self.worker)
            self.planner = Planner(self.worker.twin_path, settings.control_rate_hz, self.worker.supervisor_config)
            self.planner.start()
            self.daemon = RobotDaemon(
                robot=self.paths.robot,
                worker=self.worker,
                database=database,
                journal_dir=self.paths.journal,
                planner=self.planner,
                twin=load_twin(self.worker.twin_path) if self.worker.twin_path else default_twin(),
                plan_store=PlanStore(settings.data_dir.resolve() / "plans", settings.plan_store_max_mb * 1_000_000),
                chunk_period_s=settings.log_flush_interval_s,
            )
            self.daemon.listeners.append(lambda events: self.push(msg.EventsPush(events=events)))
            with self._links_lock:
                for link_id, web_pid in self.link_pids.items():
                    self.daemon.link_opened(link_id, web_pid, self.link_consoles.get(link_id))
            self.daemon.start()
            wait_for_estop_listener(self.paths, self.estop_listener)
            self.set_state(DaemonState.READY, f"backend {settings.backend} at {settings.control_rate_hz} Hz")
            self.push(msg.ReadyPush(names=self.hello()))
            self._stop.wait()
            self.set_state(DaemonState.STOPPING, "shutting down")
            return 0
        except Exception as error:
            log.exception("the robot daemon failed")
            self.set_state(DaemonState.FAULT, f"{type(error).__name__}: {error}"[:200])
            self._stop.wait(2.0)  # long enough for attached consoles to read why
            return 1
        finally:
            if self.estop_listener is not None:
                self.estop_listener.terminate()
            if self.daemon is not None:
                if self._stopped_by is not None:
                    self.daemon.shutdown(f"{DAEMON_STOPPED} ({self._stopped_by})")
                else:
                    self.daemon.shutdown()
            if self._restarting is not None:  # a worker being started now is ended with the daemon, not left
                self._restarting.join(WORKER_START_TIMEOUT_S)
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


ESTOP_LISTENER_START_S = 120.0  # its imports on a loaded machine; the worker's compile usually takes longer


def start_estop_listener(paths: RobotPaths) -> subprocess.Popen[bytes]:
    """The emergency-stop listener, with this daemon's settings (its environment) and log."""
    from server.robotd.estop_listener import address_file

    with contextlib.suppress(FileNotFoundError):
        address_file(paths).unlink()  # a previous listener's: the page must not be sent there
    with paths.log.open("ab") as log_file:
        return subprocess.Popen(
            [
                sys.executable,
                "-m",
                "server.robotd.estop_listener",
                "--robot",
                paths.robot,
                "--data-dir",
                str(paths.data_dir),
                "--parent-pid",
                str(os.getpid()),
            ],
            stdin=subprocess.DEVNULL,
            stdout=log_file,
            stderr=subprocess.STDOUT,
        )


def wait_for_estop_listener(paths: RobotPaths, listener: subprocess.Popen[bytes] | None) -> None:
    """Ready only once the stop listener listens (it publishes its port), or it failed: then the pages
    use /api/v1/estop and the log says why."""
    from server.robotd.estop_listener import published_port

    deadline = time.monotonic() + ESTOP_LISTENER_START_S
    while listener is not None and listener.poll() is None and time.monotonic() < deadline:
        if published_port(paths) is not None:
            return
        time.sleep(0.05)
    log.error(
        "the emergency-stop listener is not listening (exit code %s): pages use /api/v1/estop",
        listener and listener.poll(),
    )


def _unlink_stale_shared_memory(paths: RobotPaths) -> None:
    """A crashed daemon could not free its blocks; they are only names now (any mapping stays valid)."""
    if not paths.shared_memory.exists():
        return
    for name in paths.shared_memory.read_text().split():
        with contextlib.suppress(OSError):
            os.unlink(f"/dev/shm/{name.lstrip('/')}")
    paths.shared_memory.unlink()


def _serve_socket(owner: RobotDaemonProcess) -> socketserver.UnixStreamServer:
    class Handler(socketserver.StreamRequestHandler):
        def handle(self) -> None:
            line = self.rfile.readline()
            if not line:
                return
            try:
                request = msg.decode_request(line)
            except msgspec.ValidationError as error:  # named: the field and what was wrong with it
                reply = msg.DaemonReply(refusal=msg.refusal_of(InvalidFieldError("request", line[:200], str(error))))
            except msgspec.DecodeError:
                return
            else:
                if isinstance(request, msg.Hello) and request.persistent:
                    owner.serve_link(self.connection, self.rfile, request.web_pid, request.console)
                    return
                try:
                    reply = msg.DaemonReply(result=owner.handle(request))
                except Exception as error:
                    if not isinstance(error, (LookupError, RuntimeError, ValueError)):
                        log.exception("robot daemon command %r failed", request)
                    reply = msg.DaemonReply(refusal=msg.refusal_of(error))
            with contextlib.suppress(OSError):
                self.connection.sendall(msg.encode_line(reply))

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


def run_robot_daemon(settings: Settings, robot: str, started_by: str | None = None) -> int:
    """Process entry (`ssp-rehab robot`): the exit code."""
    return RobotDaemonProcess(settings, robot, started_by).run()
