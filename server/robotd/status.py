"""Where a robot daemon lives (lock, pid and socket files under the data directory) and the status
record it publishes in shared memory every 20 ms, which web processes read without asking it."""

from __future__ import annotations

import enum
import fcntl
import logging
import os
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from server.realtime.shm import Seqlock

log = logging.getLogger("ssp_rehab.robotd")
STATUS_PERIOD_S = 0.02
DAEMON_STALE_S = 0.1  # no status beat (every 20 ms) for this long: dead or hung (issue 12: within 200 ms)
COMMAND_STALE_S = 1.0  # a command is still sent to a daemon this late with its beat (a busy machine)
ROBOT_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")
REASON_BYTES = 240


LIVENESS_FIFO_PRIORITY = 10  # as the old heartbeat thread: below the worker (80) and the relay (60)


def prioritise_liveness_thread(what: str) -> None:
    """SCHED_FIFO for the calling thread: beats must not starve behind busy neighbours on a loaded machine
    (a starved beat would stop a patient's session for nothing)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(LIVENESS_FIFO_PRIORITY))
    except (OSError, AttributeError) as error:
        log.info("%s runs without real-time priority: %s", what, error)


class DaemonState(enum.IntEnum):
    ABSENT = 0  # only ever judged by the web side: no daemon, or it stopped answering
    STARTING = 1
    READY = 2
    FAULT = 3
    STOPPING = 4

    @property
    def label(self) -> str:
        return self.name.lower()


STATUS_DTYPE = np.dtype(
    [
        ("beat_ns", np.int64),  # CLOCK_MONOTONIC, shared by every process on the host
        ("state", np.uint8),
        ("pid", np.int64),
        ("active_run_id", np.int64),  # 0: none
        ("active_session_id", np.int64),
        ("reason", f"S{REASON_BYTES}"),
        ("recording_failure", f"S{2 * REASON_BYTES}"),  # it names a path  # empty while the recorder can write
    ]
)


@dataclass(frozen=True)
class PidFile:
    """A daemon's pid file: its pid and, when a console (`serve`) started it, that console's id, so that
    only that console stops it when it exits."""

    pid: int
    started_by: str | None = None

    def text(self) -> str:
        return f"{self.pid}\n" + (f"started-by {self.started_by}\n" if self.started_by else "")

    @classmethod
    def read(cls, paths: RobotPaths) -> PidFile | None:
        """None while there is none (or it is being written)."""
        try:
            lines = paths.pid.read_text().splitlines()
            pid = int(lines[0].split()[0])
        except (OSError, ValueError, IndexError):
            return None
        owners = [line.removeprefix("started-by ").strip() for line in lines[1:] if line.startswith("started-by ")]
        return cls(pid, owners[0] or None if owners else None)


@dataclass(frozen=True)
class RobotPaths:
    data_dir: Path
    robot: str

    def __post_init__(self) -> None:
        if not ROBOT_NAME.match(self.robot):
            raise ValueError(f"robot = {self.robot!r}: must be 1 to 64 letters, digits, '.', '_' or '-'")

    @property
    def directory(self) -> Path:
        return self.data_dir / "robots"

    @property
    def lock(self) -> Path:
        return self.directory / f"{self.robot}.lock"

    @property
    def pid(self) -> Path:
        return self.directory / f"{self.robot}.pid"

    @property
    def socket(self) -> Path:
        return self.directory / f"{self.robot}.sock"

    @property
    def shared_memory(self) -> Path:
        """The names of the daemon's shared-memory blocks, unlinked by the next daemon if this one crashed."""
        return self.directory / f"{self.robot}.shm"

    @property
    def log(self) -> Path:
        return self.directory / f"{self.robot}.log"

    @property
    def journal(self) -> Path:
        return self.data_dir / "runs" / self.robot


@dataclass(frozen=True)
class RobotStatus:
    """What the web side knows about its robot: `state` is starting, ready, fault or absent."""

    state: DaemonState
    reason: str
    pid: int | None = None
    active_run_id: int | None = None
    active_session_id: int | None = None
    recording_failure: str | None = None  # why the daemon's recorder cannot write (disk full, I/O error)

    @property
    def ready(self) -> bool:
        return self.state is DaemonState.READY

    def to_dict(self) -> dict[str, Any]:
        return {
            "state": self.state.label,
            "reason": self.reason,
            "pid": self.pid,
            "active_run_id": self.active_run_id,
            "active_session_id": self.active_session_id,
            "recording_failure": self.recording_failure,
        }


class StatusBlock:
    """The daemon's status record behind a seqlock (written by the daemon, read by web processes)."""

    def __init__(self, name: str | None = None) -> None:
        self.seqlock = Seqlock(STATUS_DTYPE, name)
        self._record = np.zeros(1, STATUS_DTYPE)

    @property
    def name(self) -> str:
        return self.seqlock.name

    def publish(
        self,
        state: DaemonState,
        reason: str,
        pid: int,
        run: tuple[int, int] | None,
        recording_failure: str | None = None,
    ) -> None:
        record = self._record
        record["beat_ns"] = time.monotonic_ns()
        record["state"] = int(state)
        record["pid"] = pid
        record["active_run_id"], record["active_session_id"] = run if run is not None else (0, 0)
        record["reason"] = reason.encode()[:REASON_BYTES]
        record["recording_failure"] = (recording_failure or "").encode()[: 2 * REASON_BYTES]
        self.seqlock.write(record)

    def read(self, stale_s: float = DAEMON_STALE_S) -> RobotStatus:
        record = self.seqlock.read()[0]
        age_s = (time.monotonic_ns() - int(record["beat_ns"])) * 1e-9
        pid = int(record["pid"]) or None
        if age_s > stale_s:
            return RobotStatus(
                DaemonState.ABSENT,
                f"the robot daemon (pid {pid}) stopped answering {age_s:.2f} s ago: hung or stopped",
                pid,
            )
        run_id, session_id = int(record["active_run_id"]), int(record["active_session_id"])
        return RobotStatus(
            DaemonState(int(record["state"])),
            record["reason"].decode(errors="replace"),
            pid,
            run_id or None,
            session_id or None,
            record["recording_failure"].decode(errors="replace") or None,
        )

    def close(self) -> None:
        self.seqlock.close()


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
