"""What each of the console's processes costs to start (issue 21 §9: a console start runs five of them, and the
tests start hundreds of consoles, workers and planning processes): CPU and wall time to import its entry
module in a fresh interpreter, against the same import with the libraries it used to load at start imported
first (python-control, which loads matplotlib, and scipy.signal), the same run's baseline.

No target of its own: it shows where the CI's and a console's start-up CPU goes. Each figure is the median
of REPEATS fresh interpreters; CPU is user + system of the child, from `resource`.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from typing import Any

from benchmarks.bench_cli import _child_cpu_s, median_cpu_and_wall

REPEATS = 5
PROCESSES = {
    "web": "server.app",
    "robot_daemon": "server.robotd.process",
    "stop_listener": "server.robotd.estop_listener",
    "worker": "server.realtime.worker",
    "planner": "server.robotd.planner",
}
EAGER_LIBRARIES = ("control", "matplotlib.pyplot", "scipy.signal")


def _import(module: str, preload: tuple[str, ...]) -> tuple[float, float]:
    """(CPU s, wall s) of `import module` in a fresh interpreter, after importing `preload`."""
    script = f"for name in {[*preload, module]!r}: __import__(name)\n"
    cpu_before, began = _child_cpu_s(), time.perf_counter()
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=False)
    wall_s, cpu_s = time.perf_counter() - began, _child_cpu_s() - cpu_before
    if done.returncode != 0:
        raise RuntimeError(f"import {module} failed: {done.stderr[-2000:]}")
    return cpu_s, wall_s


def _median(module: str, preload: tuple[str, ...], repeats: int) -> dict[str, float]:
    return median_cpu_and_wall([_import(module, preload) for _ in range(repeats)])


def run(quick: bool = False) -> dict[str, Any]:
    repeats = 1 if quick else REPEATS
    figures: dict[str, Any] = {"repeats": repeats, "processes": {}}
    for name, module in PROCESSES.items():
        shipped, eager = _median(module, (), repeats), _median(module, EAGER_LIBRARIES, repeats)
        figures["processes"][name] = {
            "module": module,
            "as_shipped": shipped,
            "eager_baseline": eager,
            "cpu_saved_s": round(eager["cpu_s"] - shipped["cpu_s"], 3),
            "cpu_shipped_over_eager": round(shipped["cpu_s"] / eager["cpu_s"], 3),
        }
    total_shipped = sum(p["as_shipped"]["cpu_s"] for p in figures["processes"].values())
    total_eager = sum(p["eager_baseline"]["cpu_s"] for p in figures["processes"].values())
    figures["console_start"] = {
        "cpu_s_as_shipped": round(total_shipped, 3),
        "cpu_s_eager_baseline": round(total_eager, 3),
        "cpu_shipped_over_eager": round(total_shipped / total_eager, 3),
    }
    figures["load_average_1min_at_end"] = round(os.getloadavg()[0], 1)
    return figures
