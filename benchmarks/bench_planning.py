"""How soon a classical plan is ready (issue 21, "Ready before the patient steps on"): wall time, CPU time and
peak resident memory of `core.plan.build.build_plan` (the plan, then the independent check of every sample) on
the 20-minute, 17-segment training session in `prescriptions/training_20min.json`, against its first two
segments (2 minutes) measured in the same run as the baseline.

Each measurement runs in a fresh interpreter (peak RSS is a high-water mark per process) after one small plan
has loaded the compiled kernels from numba's cache, as in the robot daemon's planning process; the figure is the
median of the repeats. CPU is user + system time of every thread. Targets: the 20-minute session planned in at
most 10 s of wall time on a quiet machine, with a peak RSS of at most 300 MB.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
from pathlib import Path
from typing import Any

PRESCRIPTION = Path(__file__).with_name("prescriptions") / "training_20min.json"
PATIENT = {"body_mass_kg": 75.0, "height_m": 1.75}
REPEATS = 3
WALL_TARGET_S = 10.0
PEAK_RSS_TARGET_MB = 300.0
CASES = {"session_20min": None, "baseline_2min": 2}  # how many of the session's segments each case plans
QUICK_CASES = {"session_4_segments": 4, "baseline_1_segment": 1}

_CHILD = """
import json, resource, sys, time
from core.plan.build import build_plan
from core.robot import default_twin

prescription, patient, segments = json.loads(sys.argv[1]), json.loads(sys.argv[2]), json.loads(sys.argv[3])
prescription["segments"] = prescription["segments"][:segments]
twin = default_twin()
build_plan({"segments": prescription["segments"][:1]}, twin, patient=patient)  # kernels loaded from the cache
rss_before_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
began, cpu_began = time.perf_counter(), time.process_time()
checked = build_plan(prescription, twin, patient=patient)
wall_s, cpu_s = time.perf_counter() - began, time.process_time() - cpu_began
report = checked.accepted()
print(json.dumps({
    "prescribed_s": sum(s["duration_s"] for s in prescription["segments"]),
    "planned_s": report.duration_s,
    "wall_s": wall_s,
    "cpu_s": cpu_s,
    "rss_before_planning_mb": rss_before_mb,
    "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    "peak_use": report.peak_use,
}))
"""


def _measure_once(segments: int | None) -> dict[str, Any]:
    prescription = json.loads(PRESCRIPTION.read_text())
    count = len(prescription["segments"]) if segments is None else segments
    arguments = [json.dumps(prescription), json.dumps(PATIENT), json.dumps(count)]
    done = subprocess.run([sys.executable, "-c", _CHILD, *arguments], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"planning {count} segments failed: {done.stderr[-2000:]}")
    figures: dict[str, Any] = json.loads(done.stdout)
    return figures


def _case(segments: int | None, repeats: int) -> dict[str, Any]:
    runs = [_measure_once(segments) for _ in range(repeats)]
    wall_s = statistics.median(r["wall_s"] for r in runs)
    cpu_s = statistics.median(r["cpu_s"] for r in runs)
    planned_s = runs[0]["planned_s"]
    return {
        "segments": segments or len(json.loads(PRESCRIPTION.read_text())["segments"]),
        "prescribed_s": runs[0]["prescribed_s"],
        "planned_s": round(planned_s, 3),  # with each segment's fade out and return to neutral
        "wall_s": round(wall_s, 2),
        "cpu_s": round(cpu_s, 2),
        "plan_s_per_wall_s": round(planned_s / wall_s, 1),
        "plan_s_per_cpu_s": round(planned_s / cpu_s, 1),
        "rss_before_planning_mb": round(statistics.median(r["rss_before_planning_mb"] for r in runs)),
        "peak_rss_mb": round(statistics.median(r["peak_rss_mb"] for r in runs)),
        "peak_use": runs[0]["peak_use"],
    }


def run(quick: bool = False) -> dict[str, Any]:
    repeats = 1 if quick else REPEATS
    load_at_start = [round(value, 2) for value in os.getloadavg()]
    (session_name, session_segments), (baseline_name, baseline_segments) = (QUICK_CASES if quick else CASES).items()
    baseline = _case(baseline_segments, repeats)
    session = _case(session_segments, repeats)
    figures: dict[str, Any] = {
        "prescription": PRESCRIPTION.name,
        "repeats": repeats,
        baseline_name: baseline,
        session_name: session,
        # 1.0: planning time grows in proportion to the plan's length; more, the long session costs extra.
        "wall_per_plan_s_over_baseline": round(
            (session["wall_s"] / session["planned_s"]) / (baseline["wall_s"] / baseline["planned_s"]), 2
        ),
        "peak_rss_growth_mb_over_baseline": session["peak_rss_mb"] - baseline["peak_rss_mb"],
        "targets": {
            "wall_s_at_most": WALL_TARGET_S,
            "wall_met": session["wall_s"] <= WALL_TARGET_S,
            "peak_rss_mb_at_most": PEAK_RSS_TARGET_MB,
            "peak_rss_met": session["peak_rss_mb"] <= PEAK_RSS_TARGET_MB,
            "note": "the wall target is for a quiet machine: read it with the load average",
        },
        "load_average_at_start": load_at_start,
        "load_average_at_end": [round(value, 2) for value in os.getloadavg()],
    }
    return figures
