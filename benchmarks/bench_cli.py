"""How soon the command line answers (issue 21 §7): CPU and wall time of `ssp-rehab --help` and of
`ssp-rehab ik --pose …` (numba's cache warm), each against the same command with the modules the eager
command line imported at start imported first: the same run's baseline.

Targets: `--help` at most 0.3 s of CPU, `ik --pose` at most 1 s of CPU. Each figure is the median of
REPEATS runs in fresh interpreters; CPU is user + system of the child, read from `resource`.
"""

from __future__ import annotations

import os
import resource
import statistics
import subprocess
import sys
import time
from typing import Any

REPEATS = 5
HELP_TARGET_CPU_S = 0.3
IK_TARGET_CPU_S = 1.0
# What `server.cli.main` imported before its commands loaded their science lazily.
EAGER_MODULES = (
    "server.prescriptions.preview",
    "core.plan.build",
    "core.tuning",
    "core.falls",
    "core.patient",
    "core.layout",
    "core.workspace",
    "core.dynamics",
    "server.hal.canopen.master",
    "server.realtime.loop",
)
COMMANDS = {"help": ["--help"], "ik": ["ik", "--pose", "0", "0", "600", "0", "0", "0"]}


def _child_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _run(arguments: list[str], preload: tuple[str, ...]) -> tuple[float, float]:
    """(CPU s, wall s) of one command in a fresh interpreter, after importing `preload`."""
    script = (
        f"import sys, runpy\nfor name in {list(preload)!r}: __import__(name)\n"
        f"sys.argv = ['ssp-rehab', *{arguments!r}]\nrunpy.run_module('server.cli.main', run_name='__main__')\n"
    )
    cpu_before, began = _child_cpu_s(), time.perf_counter()
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=False)
    wall_s, cpu_s = time.perf_counter() - began, _child_cpu_s() - cpu_before
    if done.returncode != 0:
        raise RuntimeError(f"ssp-rehab {' '.join(arguments)} failed: {done.stderr[-2000:]}")
    return cpu_s, wall_s


def median_cpu_and_wall(runs: list[tuple[float, float]]) -> dict[str, float]:
    """The medians of (CPU s, wall s) runs."""
    return {
        "cpu_s": round(statistics.median(cpu for cpu, _ in runs), 3),
        "wall_s": round(statistics.median(wall for _, wall in runs), 3),
    }


def _median(arguments: list[str], preload: tuple[str, ...], repeats: int) -> dict[str, float]:
    return median_cpu_and_wall([_run(arguments, preload) for _ in range(repeats)])


def run(quick: bool = False) -> dict[str, Any]:
    repeats = 1 if quick else REPEATS
    _run(COMMANDS["ik"], ())  # numba's cache warm for the kinematics: the target is for a warm cache
    figures: dict[str, Any] = {"repeats": repeats}
    for name, arguments in COMMANDS.items():
        lazy, eager = _median(arguments, (), repeats), _median(arguments, EAGER_MODULES, repeats)
        figures[name] = {
            "lazy": lazy,
            "eager_baseline": eager,
            "cpu_lazy_over_eager": round(lazy["cpu_s"] / eager["cpu_s"], 3),
        }
    figures["targets"] = {
        "help_cpu_s_at_most": HELP_TARGET_CPU_S,
        "help_met": figures["help"]["lazy"]["cpu_s"] <= HELP_TARGET_CPU_S,
        "ik_cpu_s_at_most": IK_TARGET_CPU_S,
        "ik_met": figures["ik"]["lazy"]["cpu_s"] <= IK_TARGET_CPU_S,
    }
    figures["load_average_1min_at_end"] = round(os.getloadavg()[0], 1)
    return figures
