"""Issue 15 §2: `ssp-rehab warm-up` (run by `scripts/console.sh` during set-up) compiles the real-time
kernels into numba's cache, so that the robot daemon's worker loads them instead of compiling them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow


def warm_up(cache_dir: Path) -> dict[str, object]:
    result = subprocess.run(
        [sys.executable, "-m", "server.cli.main", "warm-up", "--json"],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO), "NUMBA_CACHE_DIR": str(cache_dir)},
        capture_output=True,
        text=True,
        timeout=1800,  # a cold cache on a loaded machine compiles for minutes
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    outcome: dict[str, object] = json.loads(result.stdout)
    return outcome


def cached_kernels(cache_dir: Path) -> dict[str, int]:
    """numba's cache files (index .nbi and compiled code .nbc), by name, with their modification times."""
    return {str(p.relative_to(cache_dir)): p.stat().st_mtime_ns for p in cache_dir.rglob("*.nb[ic]")}


def test_the_warm_up_fills_numbas_cache_and_a_second_start_only_loads_it(tmp_path: Path) -> None:
    cache_dir = tmp_path / "numba-cache"
    first = warm_up(cache_dir)
    assert first["control_rate_hz"] == 1000
    compiled = cached_kernels(cache_dir)
    # The tick plays a checked plan through the twin's command kernel (core/twin_kernels.py).
    tick_kernels = [name for name in compiled if "twin_command_kernel" in name]
    assert tick_kernels, f"no tick-path kernel was cached: {sorted(compiled)}"
    # The worker compiles the same tick path at its start (compile_tick_path): from a warm cache nothing
    # is compiled again, so no cache file is written again.
    warm_up(cache_dir)
    assert cached_kernels(cache_dir) == compiled
