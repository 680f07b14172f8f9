"""The robot's first start with and without the set-up warm-up (issue 15 §2).

A real console (`serve` and its robot daemon, kinematic backend) is started on an empty numba cache
(`NUMBA_CACHE_DIR` in a fresh directory: a fresh install), stopped, then `ssp-rehab warm-up` fills a
second fresh cache and the console starts on it: the same run's baseline is the cold start. Measured
from launching `serve` to `/health` saying the robot is ready. Target: after the warm-up the robot is
ready in at most half the cold start's time (the kernels are loaded, not compiled).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.fault_harness import ADMIN, Console

TARGET_RATIO = 0.5


def _ready_after_s(data_dir: Path, cache_dir: Path) -> float:
    console = Console(data_dir, extra_env={"NUMBA_CACHE_DIR": str(cache_dir)})
    data_dir.mkdir(parents=True)
    created = console.cli("create-user", "--username", ADMIN[0], "--password", ADMIN[1], "--role", "admin")
    assert created.returncode == 0, created.stderr
    began = time.perf_counter()
    try:
        console.start()
        return time.perf_counter() - began
    finally:
        console.stop()


def run(quick: bool = False) -> dict[str, Any]:
    del quick  # one cold and one warm start are the smallest meaningful run
    with tempfile.TemporaryDirectory(prefix="bench-warmup-") as scratch:
        root = Path(scratch)
        cold_s = _ready_after_s(root / "cold", root / "cold-cache")
        warm_cache = root / "warm-cache"
        began = time.perf_counter()
        warmed = Console(root / "unused", extra_env={"NUMBA_CACHE_DIR": str(warm_cache)}).cli("warm-up", "--json")
        warm_up_s = time.perf_counter() - began
        assert warmed.returncode == 0, warmed.stderr
        warm_s = _ready_after_s(root / "warm", warm_cache)
    ratio = warm_s / cold_s
    return {
        "robot_ready_after_cold_start_s": round(cold_s, 1),
        "warm_up_command_s": round(warm_up_s, 1),
        "warm_up_compile_s": json.loads(warmed.stdout)["elapsed_s"],
        "robot_ready_after_warm_up_s": round(warm_s, 1),
        "warm_over_cold": round(ratio, 2),
        "target_warm_over_cold_at_most": TARGET_RATIO,
        "met": ratio <= TARGET_RATIO,
        "load_average_1min_at_end": round(os.getloadavg()[0], 1),
    }
