"""The emergency stop's one way to the latch, shared by the stop listener (`server.robotd.estop_listener`,
which the console page uses) and the web route `POST /api/v1/estop` (scripts): store the request in the
worker's control block, wait for the worker to show it latched, and say truthfully what happened.

"No robot process" (503) only when the daemon's process is gone (nobody holds its lock). A daemon or
worker that is alive but slow (stopped, starved) gets "requested, not confirmed within N ms" (504): the
request stays in the control block and the worker latches it when it next runs.
"""

from __future__ import annotations

import datetime as dt
import enum
import time
from dataclasses import dataclass
from typing import Any

from server.realtime.shm import ControlBlock, Seqlock

ESTOP_CONFIRM_TIMEOUT_S = 0.25  # the worker checks the flag every tick (1 ms); a live one confirms at once
CONFIRM_POLL_S = 0.0005
STATE_READ_TIMEOUT_S = 0.02  # a worker stopped mid-write holds its seqlock: that is "not confirmed", not a hang
NO_ROBOT_PROCESS = "no robot process: the drives stop on their own heartbeat loss"
ESTOP_LATCHED = "emergency stop latched by the robot"


class StopOutcome(enum.Enum):
    CONFIRMED = "confirmed"
    NOT_CONFIRMED = "not_confirmed"  # requested; the worker has not shown it latched (slow or stopped)
    NO_WORKER = "no_worker"  # the daemon lives but runs no worker yet (starting): nothing can move
    NO_DAEMON = "no_daemon"  # the daemon's process is gone


HTTP_STATUS = {
    StopOutcome.CONFIRMED: 200,
    StopOutcome.NOT_CONFIRMED: 504,
    StopOutcome.NO_WORKER: 409,
    StopOutcome.NO_DAEMON: 503,
}


@dataclass(frozen=True)
class StopAnswer:
    outcome: StopOutcome
    detail: str
    confirmed_after_ms: float | None = None

    @property
    def http_status(self) -> int:
        return HTTP_STATUS[self.outcome]

    def body(self) -> dict[str, Any]:
        if self.outcome is StopOutcome.CONFIRMED:
            return {
                "status": ESTOP_LATCHED,
                "utc": dt.datetime.now(dt.UTC).isoformat(),
                "confirmed_after_ms": self.confirmed_after_ms,
            }
        return {"detail": self.detail, "outcome": self.outcome.value}


def confirmed(after_ns: int) -> StopAnswer:
    return StopAnswer(StopOutcome.CONFIRMED, ESTOP_LATCHED, round((time.perf_counter_ns() - after_ns) * 1e-6, 3))


def unconfirmed(daemon_alive: bool, worker: ControlBlock | None, why: str, timeout_s: float) -> StopAnswer:
    """The answer when the worker did not show the stop latched within `timeout_s`. "No robot process" only
    when the process that would latch it is gone: the daemon (nobody holds its lock) or its worker."""
    if not daemon_alive:
        return StopAnswer(StopOutcome.NO_DAEMON, f"{NO_ROBOT_PROCESS} ({why}: the robot daemon is gone)")
    if worker is None:
        return StopAnswer(
            StopOutcome.NO_WORKER,
            f"nothing to stop: the robot daemon runs but its real-time worker does not yet, so nothing moves ({why})",
        )
    worker_pid = int(worker.fields["worker_pid"][0])
    if worker_pid and not process_alive(worker_pid):
        return StopAnswer(
            StopOutcome.NO_DAEMON, f"{NO_ROBOT_PROCESS} ({why}: its real-time worker, pid {worker_pid}, is gone)"
        )
    return StopAnswer(
        StopOutcome.NOT_CONFIRMED,
        f"emergency stop requested, not confirmed within {timeout_s * 1000:.0f} ms: the robot's real-time worker "
        f"has not shown it latched (slow or stopped). The stop stays requested and latches when the worker next "
        f"runs; the drives also stop on their own heartbeat loss. Use the hardware stop button. ({why})",
    )


def process_alive(pid: int) -> bool:
    """True for a process that exists and is not a zombie (a stopped one is alive: it will run again)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as stat:
            return stat.read().rsplit(b")", 1)[1].split()[0] != b"Z"
    except (OSError, IndexError):
        return False


def request_stop(control: ControlBlock, state: Seqlock) -> int:
    """Store the request; the state sequence to confirm against."""
    control.request_estop(time.perf_counter_ns())
    return state.sequence


def latched_after(state: Seqlock, sequence: int) -> bool:
    """True once the worker published two full states after the request and shows the stop latched."""
    if state.sequence < sequence + 4:
        return False
    try:
        return bool(state.read(STATE_READ_TIMEOUT_S)[0]["estop_latched"])
    except TimeoutError:
        return False


def wait_latched(state: Seqlock, sequence: int, timeout_s: float = ESTOP_CONFIRM_TIMEOUT_S) -> bool:
    """Blocking wait (the stop listener's own thread); one last look after the deadline."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if latched_after(state, sequence):
            return True
        time.sleep(CONFIRM_POLL_S)
    return latched_after(state, sequence)
