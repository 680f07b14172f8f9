"""A real console for fault injection: `ssp-rehab serve` (and its robot daemon) as separate processes,
driven over HTTP, killed and stopped with signals, and its SQLite records read directly afterwards.

Used by the defect and fault-injection tests (tests/server/test_faults.py) and `ssp-rehab bench faults`.
Every wait is event-based with a generous timeout: the tests run on a loaded 2-core machine.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import itertools
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
from sqlalchemy import create_engine, text

REPO_ROOT = Path(__file__).resolve().parent.parent
ADMIN = ("faultadmin", "fault-admin-password-1")
SHORT_SINE = {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.3, "frequency_hz": 0.5}
START_TIMEOUT_S = 900.0  # a cold numba cache on a loaded machine compiles for minutes
EVENT_TIMEOUT_S = 60.0
SERVE_EXIT_TIMEOUT_S = 300.0  # serve's exit includes its robot daemon's controlled stop and flush
# Each booking in its own hour, across every console of this process (they may share a database).
_booking_hours = itertools.count(int(time.time()) % 10_000 * 10)


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def wait_for(condition: Callable[[], Any], timeout_s: float, what: str, period_s: float = 0.02) -> Any:
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(period_s)


def descendants(pid: int) -> list[int]:
    """Every live descendant of `pid` (from /proc)."""
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        with contextlib.suppress(OSError, IndexError, ValueError):
            stat = (entry / "stat").read_text()
            parent = int(stat.rsplit(")", 1)[1].split()[1])
            children.setdefault(parent, []).append(int(entry.name))
    found, stack = [], [pid]
    while stack:
        for child in children.get(stack.pop(), []):
            found.append(child)
            stack.append(child)
    return found


def alive(pid: int) -> bool:
    """True for a running (not zombie) process."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state not in ("Z", "X")


def daemon_pid(data_dir: Path, robot: str = "twin-1") -> int | None:
    """The pid of the live robot daemon of `robot` in `data_dir` (None where there is none)."""
    path = data_dir / "robots" / f"{robot}.pid"
    with contextlib.suppress(OSError, ValueError):
        pid = int(path.read_text().split()[0])
        return pid if alive(pid) else None
    return None


def stop_robot_daemon(data_dir: Path, robot: str = "twin-1") -> None:
    """The robot daemon that a `serve` killed, or told `--keep-robot`, left running: whoever started a
    console in a test or a benchmark stops it too (SIGTERM, then SIGKILL after 60 s)."""
    pid = daemon_pid(data_dir, robot)
    if pid is None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGCONT)
        os.kill(pid, signal.SIGTERM)
    with contextlib.suppress(AssertionError):
        wait_for(lambda: not alive(pid), 60.0, "the daemon to exit", 0.1)
    if alive(pid):
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)


@dataclass
class Console:
    """One console installation (a data directory) and its running `serve` process, if any."""

    data_dir: Path
    backend: str = "kinematic"
    robot: str = "twin-1"
    port: int = field(default_factory=free_port)
    extra_env: dict[str, str] = field(default_factory=dict)
    serve_args: tuple[str, ...] = ()  # further `serve` options, e.g. ("--workers", "2")
    process: subprocess.Popen[bytes] | None = None
    token: str | None = None
    log_path: Path | None = None

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api/v1"

    def env(self) -> dict[str, str]:
        return {
            **os.environ,
            "PYTHONPATH": str(REPO_ROOT),
            "SSP_REHAB_DATA_DIR": str(self.data_dir),
            "SSP_REHAB_BACKEND": self.backend,
            "SSP_REHAB_ROBOT": self.robot,
            "SSP_REHAB_VIZ_ENABLED": "false",
            # The loaded test machine stalls the worker for tens of ms now and then; the drives' own stop is
            # tested elsewhere (test_supervisor), here it would only end sessions at random.
            "SSP_REHAB_DRIVE_COMMUNICATION_TIMEOUT_S": "1.0",
            **self.extra_env,
        }

    def cli(self, *args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "server.cli.main", *args],
            cwd=REPO_ROOT,
            env=self.env(),
            capture_output=True,
            text=True,
            timeout=600,
            check=False,
        )

    # --- the service ------------------------------------------------------------------------------

    def start(self, *, wait_robot: bool = True) -> None:
        self.data_dir.mkdir(parents=True, exist_ok=True)
        if not (self.data_dir / "ssp-rehab.sqlite3").exists():
            created = self.cli("create-user", "--username", ADMIN[0], "--password", ADMIN[1], "--role", "admin")
            assert created.returncode == 0, created.stderr
        self.log_path = self.data_dir / f"serve-{self.port}-{time.time_ns()}.log"
        with self.log_path.open("wb") as log:
            self.process = subprocess.Popen(
                [sys.executable, "-m", "server.cli.main", "serve", "--port", str(self.port), *self.serve_args],
                cwd=REPO_ROOT,
                env=self.env(),
                stdout=log,
                stderr=subprocess.STDOUT,
            )
        wait_for(self._answers, START_TIMEOUT_S, f"the console on port {self.port} ({self.log_path})", 0.2)
        if wait_robot:
            wait_for(self.robot_ready, START_TIMEOUT_S, f"the robot to be ready ({self.log_path})", 0.2)
        self.login()

    def _answers(self) -> bool:
        if self.process is not None and self.process.poll() is not None:
            raise AssertionError(f"serve exited with {self.process.returncode}: {self.log_text()[-3000:]}")
        try:
            return httpx.get(f"{self.url}/health", timeout=5.0).status_code == 200
        except httpx.HTTPError:
            return False

    def health(self) -> dict[str, Any]:
        response = httpx.get(f"{self.url}/health", timeout=10.0)
        result: dict[str, Any] = response.json()
        return result

    def robot_ready(self) -> bool:
        return bool(self.health().get("robot_connected"))

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path and self.log_path.exists() else ""

    def signal(self, signum: int) -> None:
        assert self.process is not None
        os.kill(self.process.pid, signum)

    def kill(self) -> None:
        """kill -9 of the web process only (its children, if any, are left to react as they would)."""
        assert self.process is not None
        os.kill(self.process.pid, signal.SIGKILL)
        self.process.wait(30)
        self.process = None

    def stop(self) -> None:
        """A clean shutdown of the web process and of every process it started or left behind."""
        if self.process is not None:
            with contextlib.suppress(ProcessLookupError):
                os.kill(self.process.pid, signal.SIGCONT)
                self.process.terminate()
            try:
                self.process.wait(SERVE_EXIT_TIMEOUT_S)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(30)
            self.process = None
        self.stop_daemon()

    def daemon_pid(self) -> int | None:
        """The robot daemon's pid from its pid file (None where there is no daemon)."""
        return daemon_pid(self.data_dir, self.robot)

    def stop_daemon(self) -> None:
        stop_robot_daemon(self.data_dir, self.robot)

    # --- HTTP ---------------------------------------------------------------------------------------

    def headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"} if self.token else {}

    def login(self) -> None:
        response = httpx.post(f"{self.url}/auth/login", json={"username": ADMIN[0], "password": ADMIN[1]}, timeout=30.0)
        assert response.status_code == 200, response.text
        self.token = response.json()["access_token"]

    def get(self, path: str, **kwargs: Any) -> httpx.Response:
        return httpx.get(f"{self.url}{path}", headers=self.headers(), timeout=kwargs.pop("timeout", 60.0), **kwargs)

    def post(self, path: str, *, auth: bool = True, **kwargs: Any) -> httpx.Response:
        headers = self.headers() if auth else {}
        return httpx.post(f"{self.url}{path}", headers=headers, timeout=kwargs.pop("timeout", 300.0), **kwargs)

    def book(self, *, segments: list[dict[str, Any]] | None = None, robot: str | None = None) -> int:
        """A patient, a prescription and one booking (each in its own hour); returns the booking (session) id."""
        number = f"F-{time.time_ns()}"
        patient = self.post(
            "/patients",
            json={
                "identifier": number,
                "name": "Fault Testperson",
                "date_of_birth": "1950-02-03",
                "sex": "female",
                "height_m": 1.65,
                "body_mass_kg": 60.0,
            },
        )
        assert patient.status_code == 201, patient.text
        segments = segments or [{"cue": SHORT_SINE, "duration_s": 60.0}]
        prescription = self.post(
            "/prescriptions", json={"patient_id": patient.json()["id"], "name": "fault test", "segments": segments}
        )
        assert prescription.status_code == 201, prescription.text
        start = dt.datetime(2031, 1, 1, tzinfo=dt.UTC) + dt.timedelta(hours=next(_booking_hours))
        booking = self.post(
            "/sessions",
            json={
                "patient_id": patient.json()["id"],
                "prescription_id": prescription.json()["id"],
                "robot": robot or self.robot,
                "start": start.isoformat(),
                "duration_s": 600,
            },
        )
        assert booking.status_code == 201, booking.text
        return int(booking.json()[0]["id"])

    def run(self, run_id: int) -> dict[str, Any]:
        result: dict[str, Any] = self.get(f"/runs/{run_id}").json()
        return result

    def runs(self, session_id: int) -> list[dict[str, Any]]:
        result: list[dict[str, Any]] = self.get(f"/sessions/{session_id}/runs").json()
        return result

    def acknowledge_pending(self) -> int | None:
        """The therapist acknowledges the robot's last stop that moved the patient (an emergency stop, an
        interruption, a fault, a fall, a limit stop), as a start needs; the run id, or None if none waited."""
        pending = self.get("/reviews/pending", params={"robot": self.robot}).json()
        if pending is None:
            return None
        answer = self.post(f"/runs/{pending['run_id']}/acknowledge", json={"note": "fault test: attended to"})
        assert answer.status_code == 200, answer.text
        return int(pending["run_id"])

    def wait_moving(self, timeout_s: float = EVENT_TIMEOUT_S) -> None:
        wait_for(
            lambda: (state := self.get("/robot/state")).status_code == 200 and state.json().get("state") == "running",
            timeout_s,
            "the robot to run",
        )

    # --- the records ----------------------------------------------------------------------------------

    @contextlib.contextmanager
    def database(self) -> Iterator[Any]:
        engine = create_engine(f"sqlite:///{self.data_dir / 'ssp-rehab.sqlite3'}")
        try:
            with engine.connect() as connection:
                yield connection
        finally:
            engine.dispose()

    def events(self, run_id: int | None = None) -> list[dict[str, Any]]:
        """Session events (all, or of one run), oldest first, with their run id."""
        query = "SELECT id, run_id, kind, tick, tick_time_s, utc, detector, details, user_id FROM session_events"
        with self.database() as connection:
            if run_id is None:
                rows = connection.execute(text(query + " ORDER BY id")).mappings().all()
            else:
                rows = (
                    connection.execute(text(query + " WHERE run_id = :r ORDER BY id"), {"r": run_id}).mappings().all()
                )
        return [dict(row) for row in rows]

    def run_row(self, run_id: int) -> dict[str, Any]:
        """The run as stored, read from the database (works while the web process is stopped)."""
        with self.database() as connection:
            row = connection.execute(text("SELECT * FROM session_runs WHERE id = :r"), {"r": run_id}).mappings().one()
        return dict(row)

    def last_sample_utc_s(self, run_id: int) -> float | None:
        """UTC (POSIX s) of the last telemetry sample stored for the run."""
        from server.robotd.records import decode_chunk

        with self.database() as connection:
            blobs = connection.execute(
                text("SELECT data FROM telemetry_chunks WHERE run_id = :r ORDER BY sequence DESC LIMIT 1"),
                {"r": run_id},
            ).scalars()
            return max((float(decode_chunk(blob)["utc_s"].max()) for blob in blobs), default=None)

    def telemetry_ticks(self, run_id: int) -> tuple[int, int, int]:
        """(samples stored, first tick, last tick) of a run's telemetry chunks."""
        import numpy as np

        from server.robotd.records import decode_chunk

        with self.database() as connection:
            blobs = connection.execute(
                text("SELECT data FROM telemetry_chunks WHERE run_id = :r ORDER BY sequence"), {"r": run_id}
            ).scalars()
            chunks = [decode_chunk(blob) for blob in blobs]
        if not chunks:
            return 0, -1, -1
        ticks = np.concatenate([chunk["tick"] for chunk in chunks])
        return len(ticks), int(ticks.min()), int(ticks.max())


def in_background(function: Callable[[], Any]) -> tuple[threading.Thread, list[Any]]:
    """Run `function` in a thread; its result (or exception) lands in the returned list."""
    result: list[Any] = []

    def target() -> None:
        try:
            result.append(function())
        except Exception as error:
            result.append(error)

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    return thread, result


@contextlib.contextmanager
def small_disk(directory: Path, size_mb: int) -> Iterator[Path]:
    """A tmpfs of `size_mb` mounted at `directory` (needs root: `PermissionError` otherwise), unmounted after."""
    directory.mkdir(parents=True, exist_ok=True)
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_mb}m,mode=0700", "tmpfs", str(directory)],
        capture_output=True,
        text=True,
        check=False,
    )
    if mounted.returncode != 0:
        raise PermissionError(f"cannot mount a tmpfs at {directory}: {mounted.stderr.strip()}")
    try:
        yield directory
    finally:
        subprocess.run(["umount", "--lazy", str(directory)], check=False)


def fill_disk(directory: Path) -> Path:
    """Take every free byte of the file system holding `directory` (big blocks, then pages), as a disk that
    filled up would; delete the returned file to free the space again."""
    filler = directory / "filler"
    with filler.open("wb", buffering=0) as handle:
        for block in (b"\0" * (1 << 20), b"\0" * 4096):
            while True:
                try:
                    if handle.write(block) == 0:
                        break
                except OSError as error:
                    if error.errno != errno.ENOSPC:
                        raise
                    break
    return filler
