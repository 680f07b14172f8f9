"""Where the real-time worker runs on a shared computer, and who yields to it (issue 20, defect 8).

- **One core per worker.** Several robots (or a robot and a test bench) may run on one computer. Each
  worker claims a CPU for its life with an exclusive `flock` on a per-CPU lock file in a directory shared
  by the whole machine (`SSP_REHAB_REALTIME_LOCK_DIR`, default `/run/lock`), taken from the CPUs allowed to
  the process, highest first. The kernel drops the lock when the worker ends, however it ends. When every
  allowed CPU is claimed the worker runs unpinned and says so (log, `worker_started`, `/health`): refusing
  would stop a test bench for a warning's worth of risk, and its late-tick stop still protects the patient.
  `SSP_REHAB_REALTIME_CPU` = `auto` (default), a CPU number (claimed the same way; taken: unpinned), or
  `none` (never pin).
- **Everything else yields.** Web processes, the planning process and preview work lower their own
  priority (`lower_priority`, nice 10): on a busy machine the daemon and its worker win the CPU.
- **What the OS refused is said plainly** (`RealtimeReport`), with what to configure.
"""

from __future__ import annotations

import contextlib
import fcntl
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

log = logging.getLogger("ssp_rehab.realtime")

DEFAULT_LOCK_DIR = Path("/run/lock")
LOCK_DIR_ENVIRONMENT = "SSP_REHAB_REALTIME_LOCK_DIR"
CPU_ENVIRONMENT = "SSP_REHAB_REALTIME_CPU"
BACKGROUND_NICE = 10  # web processes, planning, previews and exports: below the daemon (0) and its worker
HOW_TO_FIX = (
    "grant the robot daemon real-time scheduling: in its systemd unit LimitRTPRIO=80 (or "
    "AmbientCapabilities=CAP_SYS_NICE; CPUSchedulingPolicy=fifo applies to the whole daemon), by hand "
    "`ulimit -r 80` before `ssp-rehab robot` or `setcap cap_sys_nice+ep` on its Python, in a container "
    "--cap-add=SYS_NICE --ulimit rtprio=80; check the worker with `chrt -p PID`"
)


def lock_dir() -> Path:
    """The machine-wide directory of the per-CPU claims."""
    configured = os.environ.get(LOCK_DIR_ENVIRONMENT)
    return Path(configured) if configured else DEFAULT_LOCK_DIR


def parse_cpu_request(value: object) -> int | str:
    """`auto`, `none` or a CPU number, or ValueError naming `realtime_cpu`."""
    if isinstance(value, int) and not isinstance(value, bool) and value >= 0:
        return value
    text = str(value).strip().lower()
    if text in ("auto", "none"):
        return text
    if text.isdigit():
        return int(text)
    raise ValueError(f"realtime_cpu = {value!r}: must be 'auto', 'none' or a CPU number (0, 1, …)")


@dataclass
class CpuClaim:
    """The CPU this process holds (None: unpinned) and why, if it got none."""

    cpu: int | None
    descriptor: int | None = None
    refusal: str | None = None

    def release(self) -> None:
        if self.descriptor is not None:
            with contextlib.suppress(OSError):
                os.close(self.descriptor)  # closing drops the flock
            self.descriptor = None


def _try_claim(directory: Path, cpu: int) -> int | None:
    """The locked descriptor of CPU `cpu`'s claim file, or None when another process holds it."""
    path = directory / f"ssp-rehab-realtime-cpu{cpu}.lock"
    descriptor = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    with contextlib.suppress(OSError):
        os.fchmod(descriptor, 0o666)  # other users' installations on this computer claim through it too
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(descriptor)
        return None
    os.ftruncate(descriptor, 0)
    os.write(descriptor, f"{os.getpid()}\n".encode())
    return descriptor


def claim_cpu(request: int | str = "auto", directory: Path | None = None) -> CpuClaim:
    """Claim a CPU no other real-time worker on this computer holds (see the module's docstring)."""
    request = parse_cpu_request(request)
    if request == "none":
        return CpuClaim(None, refusal=f"not pinned ({CPU_ENVIRONMENT}=none)")
    allowed = sorted(os.sched_getaffinity(0), reverse=True)
    if isinstance(request, int) and request not in allowed:
        return CpuClaim(None, refusal=f"{CPU_ENVIRONMENT}={request}: not among the CPUs allowed {sorted(allowed)}")
    directory = directory or lock_dir()
    try:
        directory.mkdir(parents=True, exist_ok=True)
        for cpu in [request] if isinstance(request, int) else allowed:
            descriptor = _try_claim(directory, cpu)
            if descriptor is not None:
                return CpuClaim(cpu, descriptor)
    except OSError as error:
        return CpuClaim(None, refusal=f"cannot claim a CPU in {directory} ({error}): running unpinned")
    taken = f"CPU {request} is" if isinstance(request, int) else f"every allowed CPU {sorted(allowed)} is"
    return CpuClaim(
        None,
        refusal=f"{taken} claimed by another real-time worker on this computer (locks in {directory}): running "
        f"unpinned, late ticks likely; run fewer robots here or give this one a free CPU ({CPU_ENVIRONMENT})",
    )


def lower_priority(what: str, nice: int = BACKGROUND_NICE) -> None:
    """Nice the calling thread (and the threads and processes it starts later) to at least `nice`.

    On Linux the nice value is per thread: call it on a process's main thread before it starts others.
    Work that must not yield (a beat to the robot daemon) runs SCHED_FIFO where permitted
    (`server.robotd.status.prioritise_liveness_thread`), which nice does not touch."""
    try:
        current = os.getpriority(os.PRIO_PROCESS, 0)
        if current < nice:
            os.setpriority(os.PRIO_PROCESS, 0, nice)
    except (OSError, AttributeError) as error:
        log.info("%s keeps its priority: %s", what, error)


@dataclass
class RealtimeReport:
    """What `/health` says about the worker's scheduling: what was asked, what was granted, how to fix."""

    policy: str  # "fifo" or "other"
    priority: int | None
    cpu: int | None
    granted: bool
    refusals: list[str] = field(default_factory=list)

    @classmethod
    def from_setup(cls, setup: dict[str, Any]) -> RealtimeReport:
        priority = setup.get("fifo_priority")
        refusals = list(setup.get("refusals") or [])
        return cls(
            "fifo" if priority else "other",
            priority,
            setup.get("cpu"),
            granted=bool(priority) and setup.get("cpu") is not None,
            refusals=refusals,
        )

    def to_dict(self) -> dict[str, Any]:
        how_to_fix = None
        if not self.granted:
            fixes = [HOW_TO_FIX] if self.policy != "fifo" else []
            if self.cpu is None:
                fixes.append(f"give the worker a CPU of its own: {CPU_ENVIRONMENT}, or fewer robots on this computer")
            how_to_fix = "; ".join(fixes)
        return {
            "policy": self.policy,
            "priority": self.priority,
            "cpu": self.cpu,
            "granted": self.granted,
            "refusals": self.refusals,
            "how_to_fix": how_to_fix,
        }
