"""The emergency-stop listener: a process of its own, started by the robot daemon (its child, ended with it),
that does nothing but latch the stop in the worker's control block, wait for the worker's confirmation and
answer (`POST /estop`). It shares no event loop, thread pool or interpreter lock with the web processes'
API work (exports, uploads, many clients) nor with the daemon's own (planning, journals, the database), so
nothing on the server can hold a stop up. The console page's red button and Escape key use it.

Why beside the daemon and not beside each web process: one per robot (however many web processes `serve
--workers` runs), it lives exactly as long as the daemon whose worker it stops, and it knows that worker's
control block from the daemon's own list of blocks (re-read when a new worker is started).

Browsers: the page learns the address from `GET /api/v1/health` (`estop`), reaches it on the console's
host name and this port, or through a reverse proxy at `estop_public_url`. No login is needed (as for
`/api/v1/estop`). A request naming a foreign `Origin` is refused before anything is latched, and only the
console's own origin gets CORS headers, so no other site can stop the robot or read an answer. Who asked is
audited afterwards by the daemon (`estop_audit`: the token the request carried, checked there), never
before the latch.
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import errno
import http.server
import json
import logging
import logging.handlers
import os
import queue
import signal
import threading
import time
from http.cookies import SimpleCookie
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

# Imported at start, not at the first stop: an import holds the interpreter lock for most of a second
# (server.messages), and a second stop arriving meanwhile waited for it (bench faults: 250–370 ms).
from server.messages import AuditListenerStop, exchange
from server.realtime.shm import ControlBlock, Seqlock, load_kernels
from server.realtime.telemetry import TELEMETRY_DTYPE
from server.robotd import estop
from server.robotd.status import RobotPaths, daemon_running, prioritise_liveness_thread
from server.settings import Settings

log = logging.getLogger("ssp_rehab.estop_listener")
STOP_PATH = "/estop"
BIND_RETRY_S = 10.0  # a listener of a daemon that just died may still hold a fixed port
AUDIT_TIMEOUT_S = 30.0
PR_SET_PDEATHSIG = 1


def address_file(paths: RobotPaths) -> Path:
    """Where the listener publishes its port (JSON), for the web processes' /health."""
    return paths.directory / f"{paths.robot}.estop"


def published_port(paths: RobotPaths) -> int | None:
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        return int(json.loads(address_file(paths).read_text())["port"])
    return None


def page_stop_url(settings: Settings, paths: RobotPaths, host: str | None, scheme: str) -> str | None:
    """Where the console page sends its stop: `estop_public_url` (a reverse proxy), else the console's own
    host name with the listener's port; None when no listener runs or an https page could not reach its
    plain-http port (the page then uses /api/v1/estop)."""
    if settings.estop_public_url:
        return settings.estop_public_url
    port = published_port(paths)
    hostname = urlsplit(f"//{host or ''}").hostname
    if port is None or not hostname or scheme != "http":
        return None
    return f"http://{f'[{hostname}]' if ':' in hostname else hostname}:{port}{STOP_PATH}"


class WorkerBlocks:
    """The worker's control block and state, attached by the names the daemon lists in `robots/NAME.shm`
    (status, control, state, ...), again whenever that list changes (a new worker)."""

    def __init__(self, paths: RobotPaths) -> None:
        self.paths = paths
        self._stamp: int | None = None
        self._lock = threading.Lock()
        self.control: ControlBlock | None = None
        self.state: Seqlock | None = None

    def current(self) -> tuple[ControlBlock, Seqlock] | None:
        with contextlib.suppress(OSError):
            stamp = self.paths.shared_memory.stat().st_mtime_ns
            if stamp != self._stamp:
                with self._lock:
                    names = self.paths.shared_memory.read_text().split()
                    if len(names) >= 3 and (self.control is None or self.control.name != names[1]):
                        self.control, self.state = ControlBlock(names[1]), Seqlock(TELEMETRY_DTYPE, names[2])
                    self._stamp = stamp
        if self.control is None or self.state is None:
            return None
        return self.control, self.state


class OriginCheck:
    """Scripts (no Origin) and the console's own pages may stop; other sites may not."""

    def __init__(self, settings: Settings) -> None:
        self.configured = {origin.strip().rstrip("/").lower() for origin in settings.allowed_origins}
        self.console_port = settings.console_port

    def allowed(self, origin: str | None, host: str | None) -> bool:
        if origin is None:
            return True
        origin = origin.strip().rstrip("/").lower()
        if origin in self.configured:
            return True
        parts, own = urlsplit(origin), urlsplit(f"//{(host or '').lower()}")
        if parts.scheme not in ("http", "https") or not parts.hostname:
            return False
        if parts.netloc == own.netloc:  # behind a reverse proxy: the page's own origin
            return True
        console = self.console_port
        return console is not None and parts.hostname == own.hostname and parts.port == console


class StopListener:
    def __init__(self, settings: Settings, paths: RobotPaths) -> None:
        self.settings, self.paths = settings, paths
        load_kernels()  # the worker's blocks are attached later, often after this start: not in a stop
        self.blocks = WorkerBlocks(paths)
        self.origins = OriginCheck(settings)
        self.timeout_s = estop.ESTOP_CONFIRM_TIMEOUT_S

    def stop(self) -> estop.StopAnswer:
        """Latch, wait for the worker, answer: nothing else comes first."""
        blocks = self.blocks.current()
        started_ns = time.perf_counter_ns()
        if blocks is not None:
            control, state = blocks
            sequence = estop.request_stop(control, state)
            if estop.wait_latched(state, sequence, self.timeout_s):
                return estop.confirmed(started_ns)
        return estop.unconfirmed(
            daemon_running(self.paths),
            blocks[0] if blocks is not None else None,
            f"stop listener of robot {self.paths.robot!r}",
            self.timeout_s,
        )

    def audit(self, token: str | None, answer: estop.StopAnswer) -> None:
        """Who asked, checked and recorded by the daemon (it ends the run too), after the answer."""
        try:
            exchange(
                str(self.paths.socket), AuditListenerStop(token=token, outcome=answer.outcome.value), AUDIT_TIMEOUT_S
            )
        except (OSError, EOFError) as error:
            log.error("the emergency stop could not be audited (robot daemon: %s)", error)
        except Exception as error:
            log.error("the robot daemon did not record the emergency stop: %s", error)


def _handler(listener: StopListener) -> type[http.server.BaseHTTPRequestHandler]:
    cookie_name = listener.settings.cookie_name

    class Handler(http.server.BaseHTTPRequestHandler):
        server_version = "ssp-rehab-estop"
        sys_version = ""
        # TCP_NODELAY: the answer's headers and body are two writes; with Nagle's algorithm the body would
        # wait for the requester's delayed acknowledgement of the headers (40–200 ms on Linux).
        disable_nagle_algorithm = True

        def do_POST(self) -> None:
            if urlsplit(self.path).path.rstrip("/") != STOP_PATH:
                self._answer(404, {"detail": f"path = {self.path!r}: the stop listener serves POST {STOP_PATH}"})
                return
            origin = self.headers.get("Origin")
            if not listener.origins.allowed(origin, self.headers.get("Host")):
                self._answer(403, {"detail": f"origin = {origin!r}: not this console's; nothing was stopped"})
                return
            answer = listener.stop()
            self._answer(answer.http_status, answer.body(), origin)
            listener.audit(self._token(), answer)

        def do_OPTIONS(self) -> None:
            origin = self.headers.get("Origin")
            if not listener.origins.allowed(origin, self.headers.get("Host")):
                self._answer(403, {"detail": f"origin = {origin!r}: not this console's"})
                return
            self._answer(204, None, origin, preflight=True)

        def _token(self) -> str | None:
            scheme, _, credentials = self.headers.get("Authorization", "").partition(" ")
            if scheme.lower() == "bearer" and credentials.strip():
                return credentials.strip()
            cookies = SimpleCookie()
            with contextlib.suppress(Exception):
                cookies.load(self.headers.get("Cookie", ""))
            morsel = cookies.get(cookie_name)
            return morsel.value if morsel is not None and morsel.value else None

        def _answer(self, code: int, body: Any, origin: str | None = None, preflight: bool = False) -> None:
            data = b"" if body is None else json.dumps(body).encode()
            self.send_response(code)
            if origin is not None:  # only ever an allowed one: the console's own page
                self.send_header("Access-Control-Allow-Origin", origin)
                self.send_header("Access-Control-Allow-Credentials", "true")
                self.send_header("Vary", "Origin")
                if preflight:
                    self.send_header("Access-Control-Allow-Methods", "POST")
                    self.send_header("Access-Control-Allow-Headers", "Authorization, Content-Type, X-Requested-With")
                    self.send_header("Access-Control-Max-Age", "600")
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            if body is not None:
                self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            with contextlib.suppress(OSError):
                self.wfile.write(data)
                self.wfile.flush()

        def log_message(self, format: str, *args: Any) -> None:
            log.info("%s %s", self.address_string(), format % args)

    return Handler


class _Server(http.server.ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = 64


def bind(listener: StopListener) -> _Server:
    """On `estop_port`; with 0, the port of the last listener of this robot when it is free (a page that
    loaded earlier keeps reaching it), else any free one."""
    settings = listener.settings
    wanted = settings.estop_port or published_port(listener.paths) or 0
    deadline = time.monotonic() + BIND_RETRY_S
    while True:
        try:
            return _Server((settings.estop_host, wanted), _handler(listener))
        except OSError as error:
            if error.errno != errno.EADDRINUSE:
                raise
            if not settings.estop_port:
                wanted = 0  # the remembered port is taken by someone else: any free one
            elif time.monotonic() > deadline:
                raise
            else:
                time.sleep(0.2)


def _end_with_parent() -> None:
    """Linux: SIGKILL when the daemon ends, however it ends (a stop path must not outlive its robot)."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)


def serve(settings: Settings, robot: str, parent_pid: int | None = None) -> int:
    _end_with_parent()
    if parent_pid is not None and os.getppid() != parent_pid:
        return 1  # the daemon died before the death signal was armed
    paths = RobotPaths(settings.data_dir.resolve(), robot)
    listener = StopListener(settings, paths)
    listener.blocks.current()  # attach now, not inside the first stop
    server = bind(listener)
    port = server.server_address[1]
    address_file(paths).write_text(json.dumps({"port": port, "host": settings.estop_host, "pid": os.getpid()}))
    log.info("emergency-stop listener of %s on %s:%s", robot, settings.estop_host, port)
    signal.signal(signal.SIGTERM, lambda *_: threading.Thread(target=server.shutdown, daemon=True).start())
    try:
        server.serve_forever(poll_interval=0.5)
    finally:
        server.server_close()
    return 0


LOG_QUEUE_RECORDS = 10_000  # beyond this, while the log cannot be written, lines are dropped, never stops
LOG_FLUSH_AT_EXIT_S = 2.0


class _DroppingQueueHandler(logging.handlers.QueueHandler):
    def enqueue(self, record: logging.LogRecord) -> None:
        with contextlib.suppress(queue.Full):
            self.queue.put_nowait(record)


def _log_off_the_stop_path() -> logging.handlers.QueueListener:
    """SCHED_FIFO for the listener, and its log lines written by a thread of their own. A write to the log
    file can wait for the disk (dirty-page throttling while large exports are written: a stop took 250–350
    ms), and the request handler logs before it answers; the stop's answer must not wait for it. The writer
    starts after the priority is set, so it inherits it: a normal-priority thread that a busy machine
    preempts while it holds the interpreter lock would hold up the stop's thread (priority inversion)."""
    records: queue.Queue[logging.LogRecord] = queue.Queue(LOG_QUEUE_RECORDS)
    writer = logging.StreamHandler()
    writer.setFormatter(logging.Formatter("%(asctime)s estop %(levelname)s [%(name)s] %(message)s"))
    queued = _DroppingQueueHandler(records)
    queued.setFormatter(logging.Formatter("%(message)s"))  # the message only: the writer adds the rest
    logging.basicConfig(level=logging.INFO, handlers=[queued])
    prioritise_liveness_thread("the emergency-stop listener")  # every thread started after this inherits it
    written = logging.handlers.QueueListener(records, writer)
    written.start()
    return written


def main() -> int:
    parser = argparse.ArgumentParser(description="The emergency-stop listener of one robot daemon.")
    parser.add_argument("--robot", required=True)
    parser.add_argument("--data-dir", required=True, type=Path)
    parser.add_argument("--parent-pid", type=int, default=None)
    arguments = parser.parse_args()
    written = _log_off_the_stop_path()
    code = 1
    try:
        code = serve(Settings(data_dir=arguments.data_dir), arguments.robot, arguments.parent_pid)
    finally:  # the last lines, unless the log still cannot be written: then the listener ends without them
        flush = threading.Thread(target=written.stop, daemon=True)
        flush.start()
        flush.join(LOG_FLUSH_AT_EXIT_S)
        if flush.is_alive():
            os._exit(code)  # logging's own shutdown would wait for the stuck write
    return code


if __name__ == "__main__":
    raise SystemExit(main())
