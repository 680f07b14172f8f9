"""The fixed-rate loop: absolute deadlines on `perf_counter_ns`, a sleep then a spin to each deadline.

Deadlines are k·period after the start, never "now + period", so lateness does not accumulate. The
thread sleeps until `spin_ns` before the deadline (the kernel's wake-up jitter is tens of µs) and spins
the rest. `configure_realtime` claims a CPU of its own (server.realtime.scheduling), asks for
SCHED_FIFO and a 1 µs timer slack, and reports what the system refused instead of failing: the loop
still runs, only with more jitter.
"""

from __future__ import annotations

import ctypes
import gc
import os
import time
from dataclasses import dataclass, field
from typing import Any

from core.errors import InvalidValueError
from server.realtime.scheduling import CpuClaim, claim_cpu

CONTROL_RATE_RANGE_HZ = (250, 2000)
LATE_THRESHOLD_NS = 500_000  # a tick that starts more than 500 µs after its deadline counts as late
_PR_SET_TIMERSLACK = 29


class LoopConfigError(InvalidValueError):
    """An invalid control-loop setting."""


def validate_control_rate(control_rate_hz: object) -> int:
    """The control rate as an int, or `LoopConfigError` naming `control_rate_hz`."""
    low, high = CONTROL_RATE_RANGE_HZ
    if isinstance(control_rate_hz, bool) or not isinstance(control_rate_hz, int) or not low <= control_rate_hz <= high:
        raise LoopConfigError("control_rate_hz", control_rate_hz, f"must be an integer in [{low}, {high}] Hz")
    return control_rate_hz


class FixedRateLoop:
    """`wait()` returns at each deadline k·period; it reports how late the tick starts."""

    def __init__(self, control_rate_hz: int, *, spin_ns: int = 150_000) -> None:
        self.control_rate_hz = validate_control_rate(control_rate_hz)
        self.period_ns = 1_000_000_000 // self.control_rate_hz
        self.spin_ns = spin_ns
        self.skipped_ticks = 0
        self.rebase()

    def rebase(self) -> None:
        """Start a fresh deadline grid from now (after a deliberate pause of the loop)."""
        self.next_deadline_ns = time.perf_counter_ns() + self.period_ns

    def wait(self) -> int:
        """Sleep and spin to the next deadline; returns the lateness (ns) of this tick's start.

        When a tick overran by more than a whole period, the missed deadlines are skipped (counted in
        `skipped_ticks`) instead of being run back to back.
        """
        deadline = self.next_deadline_ns
        now = time.perf_counter_ns()
        remaining = deadline - now - self.spin_ns
        if remaining > 0:
            time.sleep(remaining * 1e-9)
        while (now := time.perf_counter_ns()) < deadline:
            pass
        lateness = now - deadline
        behind = lateness // self.period_ns
        if behind:
            self.skipped_ticks += behind
        self.next_deadline_ns = deadline + (behind + 1) * self.period_ns
        return lateness


@dataclass
class RealtimeSetup:
    """What `configure_realtime` obtained; `refusals` say what the system did not permit."""

    cpu: int | None = None
    fifo_priority: int | None = None
    timer_slack_ns: int | None = None
    gc_frozen: bool = False
    refusals: list[str] = field(default_factory=list)
    claim: CpuClaim | None = None  # held for the process's life: another robot's worker never takes this CPU

    def to_dict(self) -> dict[str, Any]:
        return {"cpu": self.cpu, "fifo_priority": self.fifo_priority, "refusals": list(self.refusals)}

    def release(self) -> None:
        if self.claim is not None:
            self.claim.release()


def configure_realtime(cpu: int | str | None = "auto", fifo_priority: int | None = 80) -> RealtimeSetup:
    """Claim and pin a CPU no other worker on this computer holds (`server.realtime.scheduling`; `cpu`:
    `auto`, `none` or a number), ask for SCHED_FIFO (`fifo_priority` None: do not), shrink the timer slack."""
    setup = RealtimeSetup()
    claim = claim_cpu("auto" if cpu is None else cpu)
    setup.claim = claim
    if claim.refusal is not None:
        setup.refusals.append(f"CPU not pinned: {claim.refusal}")
    if claim.cpu is not None:
        try:
            os.sched_setaffinity(0, {claim.cpu})
            setup.cpu = claim.cpu
        except (OSError, AttributeError) as error:
            claim.release()
            setup.refusals.append(f"CPU affinity refused: {error}")
    if fifo_priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo_priority))
            setup.fifo_priority = fifo_priority
        except (OSError, AttributeError) as error:
            setup.refusals.append(f"SCHED_FIFO priority {fifo_priority} refused ({error}); running SCHED_OTHER")
    else:
        setup.refusals.append("SCHED_FIFO not requested; running SCHED_OTHER")
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(_PR_SET_TIMERSLACK, 1_000, 0, 0, 0) == 0:
            setup.timer_slack_ns = 1_000
        else:
            setup.refusals.append(f"timer slack refused: errno {ctypes.get_errno()}")
    except (OSError, AttributeError) as error:
        setup.refusals.append(f"timer slack refused: {error}")
    return setup


def freeze_garbage_collector() -> None:
    """Move everything alive now out of the collector's sight and stop automatic collections: no
    collection pause can land inside a tick. The worker collects explicitly while the drives are off."""
    gc.collect()
    gc.freeze()
    gc.disable()
