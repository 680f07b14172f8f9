"""Ready before the patient steps on (issue 21): Start of a stored plan, and what a 60-minute plan costs the worker.

1. Start → first set-point: from the start request (`PlanStore.load` + `WorkerClient.load_plan` +
   `Playback.start`, which checks the approach from the measured pose) until the worker's telemetry shows
   the first tick in state running, on a real spawned worker (kinematic backend). Baseline in the same
   run: the same session unplanned (plan + check + load + start). Target ≤ 1 s for a stored 20-minute plan;
   optimal cueing plans slower than real time here, so its case is the session's first two segments.
   The end is the `utc_s` of the first running telemetry record; CPU is this process's (all threads) and,
   apart, the worker's (its 1 kHz loop runs throughout).
2. A 60-minute plan (the 20-minute session three times) in a fresh worker: its resident memory before the
   load (baseline), after the load and while playing, from /proc/PID/status, smaps_rollup and (the plan's
   own mapped files) smaps. Played pages are given back (`release_before`), so the plan's resident share
   should level off; the whole hour is not played here: the 60-minute figure is extrapolated from that
   level. Target ≤ 150 MB over baseline.
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.bench_realtime import PATIENT, _settle_estop
from core.robot import default_twin, twin_digest
from server.realtime.client import WorkerClient
from server.realtime.telemetry import SupervisorState
from server.robotd.plan_store import ARRAYS, PlanStore, plan_key
from server.robotd.planner import checked_plan
from server.robotd.playback import Playback

PRESCRIPTION = Path(__file__).with_name("prescriptions") / "training_20min.json"
START_TARGET_S = 1.0
RSS_TARGET_MB = 150.0
STORED_REPEATS = 5
# Optimal cueing plans slower than real time on this 2-core machine (70 s for 60 s): its case is the
# session's first segments, and the whole session's planning time is projected from them.
OPTIMAL_SEGMENTS = 2


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def _worker_cpu_s(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def _memory_mb(pid: int) -> dict[str, float]:
    """VmRSS / RssAnon / RssFile / RssShmem (status) and Pss (smaps_rollup), MB."""
    figures = {}
    for path, names in (
        (f"/proc/{pid}/status", ("VmRSS", "RssAnon", "RssFile", "RssShmem")),
        (f"/proc/{pid}/smaps_rollup", ("Pss",)),
    ):
        for line in Path(path).read_text().splitlines():
            name, _, value = line.partition(":")
            if name in names:
                figures[name] = round(int(value.split()[0]) / 1024, 1)
    return figures


def _plan_rss_mb(pid: int, directory: Path) -> float:
    """Resident pages of the worker's mappings of the stored plan's files (smaps)."""
    total_kb, inside = 0, False
    for line in Path(f"/proc/{pid}/smaps").read_text().splitlines():
        fields = line.split()
        if "-" in fields[0] and not fields[0].endswith(":"):  # a mapping's header line
            inside = len(fields) >= 6 and fields[5].startswith(str(directory))
        elif inside and fields[0] == "Rss:":
            total_kb += int(fields[1])
    return round(total_kb / 1024, 2)


def _prescription(segments: int | None, cueing: str, repeat: int = 1) -> dict[str, Any]:
    prescription = json.loads(PRESCRIPTION.read_text())
    prescription.pop("name", None)
    prescription["segments"] = prescription["segments"][:segments] * repeat
    prescription["cueing"] = cueing
    return prescription


def _ready(client: WorkerClient) -> None:
    """Back to a loadable state between cases, as bench_realtime does."""
    client.emergency_stop()
    _settle_estop(client)
    client.reset()


def _first_running_utc(client: WorkerClient, after_utc: float, timeout_s: float = 10.0) -> float:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        records = client.drain_telemetry()
        running = records[(records["state"] == SupervisorState.RUNNING) & (records["utc_s"] >= after_utc)]
        if len(running):
            return float(running["utc_s"][0])
        time.sleep(0.001)
    raise RuntimeError(f"no running tick within {timeout_s} s: {client.latest_state()['state']}")


def _timed_start(client: WorkerClient, prepare: Any) -> dict[str, Any]:
    """Time `prepare()` (returns the plan and its report) + load + start until the first running tick."""
    twin = default_twin()
    client.drain_telemetry()
    pid = client.worker_pid
    worker_cpu, cpu, utc, wall = _worker_cpu_s(pid), _cpu_s(), time.time(), time.perf_counter()
    plan, report = prepare()
    prepared = time.perf_counter()
    client.load_plan(plan, report)
    loaded = time.perf_counter()
    Playback(twin, plan).start(client)
    started, start_cpu = time.perf_counter(), _cpu_s() - cpu
    first = _first_running_utc(client, utc)
    return {
        "wall_s": round(first - utc, 3),
        "cpu_s": round(start_cpu, 3),
        "worker_cpu_s": round(_worker_cpu_s(pid) - worker_cpu, 3),
        "split_wall_s": {
            "plan_or_store_load": round(prepared - wall, 3),
            "worker_load_plan": round(loaded - prepared, 3),
            "approach_check_and_start": round(started - loaded, 3),
        },
        "planned_s": round(float(report["duration_s"]), 1),
    }


def _start_case(client: WorkerClient, store: PlanStore, prescription: dict[str, Any], repeats: int) -> dict[str, Any]:
    """Unplanned (baseline, once: it plans) then stored (`repeats` times) in the same worker."""
    config = client.supervisor_config
    rate = client.control_rate_hz
    twin = default_twin()
    key = plan_key(prescription, PATIENT, robot_digest=twin_digest(twin), config=config.to_dict(), control_rate_hz=rate)
    made: list[Any] = []

    def plan_now() -> tuple[Any, dict[str, Any]]:
        made[:] = checked_plan(twin, rate, config, prescription, PATIENT)
        return made[0], made[1]

    _ready(client)
    unplanned = _timed_start(client, plan_now)
    store.save(key, *made)  # not timed: the daemon does this ahead of the booking
    del made[:]
    stored_runs = []
    for _ in range(repeats):
        _ready(client)
        stored_runs.append(_timed_start(client, lambda: store.load(key)))
    stored = {
        "wall_s_median": round(statistics.median(r["wall_s"] for r in stored_runs), 3),
        "wall_s_max": max(r["wall_s"] for r in stored_runs),
        "cpu_s_median": round(statistics.median(r["cpu_s"] for r in stored_runs), 3),
        "runs": stored_runs,
    }
    return {
        "prescribed_s": sum(s["duration_s"] for s in prescription["segments"]),
        "unplanned_baseline": unplanned,
        "stored": stored,
        "wall_ratio_unplanned_over_stored": round(unplanned["wall_s"] / max(stored["wall_s_median"], 1e-6), 1),
        "cpu_ratio_unplanned_over_stored": round(unplanned["cpu_s"] / max(stored["cpu_s_median"], 1e-6), 1),
        "target_met": stored["wall_s_max"] <= START_TARGET_S,
    }


def _memory_case(store: PlanStore, prescription: dict[str, Any], play_s: float) -> dict[str, Any]:
    twin = default_twin()
    client = WorkerClient(None, "kinematic", 1000)
    config, rate = client.supervisor_config, client.control_rate_hz
    key = plan_key(prescription, PATIENT, robot_digest=twin_digest(twin), config=config.to_dict(), control_rate_hz=rate)
    planning = time.perf_counter()
    store.save(key, *checked_plan(twin, rate, config, prescription, PATIENT))
    planning_s = time.perf_counter() - planning
    plan_bytes = sum((store.path(key) / f"{name}.npy").stat().st_size for name in ARRAYS)
    client.start()
    try:
        pid = client.worker_pid
        time.sleep(2.0)
        before = _memory_mb(pid)
        plan, report = store.load(key)
        plan_dir = store.path(key)
        client.load_plan(plan, report)
        after_load = {**_memory_mb(pid), "plan_files": _plan_rss_mb(pid, store.path(key))}
        Playback(twin, plan).start(client)
        began, samples = time.monotonic(), []
        while (elapsed := time.monotonic() - began) < play_s:
            time.sleep(5.0)
            client.drain_telemetry()
            memory = _memory_mb(pid)
            samples.append({"played_s": round(elapsed + 5.0, 1), **memory, "plan_files": _plan_rss_mb(pid, plan_dir)})
        state = client.latest_state()
        played = {"state": state["state"], "plan_index": state["plan_index"]}
    finally:
        client.shutdown()
    base = before["VmRSS"]
    last = samples[-1]["VmRSS"]
    half = [s["plan_files"] for s in samples if s["played_s"] > play_s / 2]
    return {
        "prescribed_s": sum(s["duration_s"] for s in prescription["segments"]),
        "planned_s": round(float(report["duration_s"]), 1),
        "planning_wall_s_not_part_of_start": round(planning_s, 1),
        "plan_arrays_on_disk_mb": round(plan_bytes / 2**20, 1),
        "worker_rss_mb_before_load_baseline": before,
        "worker_rss_mb_after_load": after_load,
        "worker_rss_mb_while_playing": samples,
        "worker_after_play": played,
        "rss_growth_mb_after_load": round(after_load["VmRSS"] - base, 1),
        "rss_growth_mb_after_play": round(last - base, 1),
        "plan_files_rss_mb_after_play": samples[-1]["plan_files"],
        "plan_files_rss_mb_range_second_half_of_play": [min(half), max(half)] if half else None,
        "what_grows": "RssShmem is the telemetry ring being filled (bounded by its size); plan_files is the "
        "resident part of the plan's mapped arrays",
        "extrapolation": (
            f"played {play_s:.0f} s of {report['duration_s']:.0f} s, not the hour; pages more than 30 000 samples "
            "behind are given back every 2048 samples, so the plan's resident share should stay at the level of "
            "the second half of the play: the 60-minute figure is that level, extrapolated, not measured"
        ),
        "target_met": last - base <= RSS_TARGET_MB,
    }


def run(quick: bool = False) -> dict[str, Any]:
    load_at_start = [round(v, 2) for v in os.getloadavg()]
    segments = 1 if quick else None
    with tempfile.TemporaryDirectory() as directory:
        store = PlanStore(Path(directory) / "plans")
        optimal_segments = 1 if quick else OPTIMAL_SEGMENTS
        client = WorkerClient(None, "kinematic", 1000)
        client.start()
        try:
            repeats = 2 if quick else STORED_REPEATS
            classical = _start_case(client, store, _prescription(segments, "classical"), repeats)
            optimal = _start_case(client, store, _prescription(optimal_segments, "optimal"), repeats)
        finally:
            client.shutdown()
        memory = _memory_case(store, _prescription(segments, "classical", repeat=3), 10.0 if quick else 60.0)
    planning = optimal["unplanned_baseline"]["split_wall_s"]["plan_or_store_load"]
    optimal["label"] = (
        f"optimal, SHORTER than the session: its first {optimal_segments} segments ({optimal['prescribed_s']:.0f} s); "
        f"planning the 20 minutes would take about {planning / optimal['prescribed_s'] * 1200:.0f} s of wall time "
        "here (projected from this case's planning), too long for this run"
    )
    return {
        "prescription": PRESCRIPTION.name,
        "start_to_first_setpoint": {"classical": classical, "optimal": optimal},
        "wall_ratio_unplanned_over_stored_sum": round(
            sum(c["unplanned_baseline"]["wall_s"] for c in (classical, optimal))
            / max(sum(c["stored"]["wall_s_median"] for c in (classical, optimal)), 1e-6),
            1,
        ),
        "worker_memory_60min_plan": memory,
        "targets": {
            "start_s_at_most": START_TARGET_S,
            "start_met_classical": classical["target_met"],
            "start_met_optimal": optimal["target_met"],
            "rss_growth_mb_at_most": RSS_TARGET_MB,
            "rss_met": memory["target_met"],
        },
        "load_average_at_start": load_at_start,
        "load_average_at_end": [round(v, 2) for v in os.getloadavg()],
        "note": "wall times on a shared 2-core machine: read them with the load average"
        + ("; QUICK: shortened, not for RESULTS.md" if quick else ""),
    }
