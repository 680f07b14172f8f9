"""Timing helpers shared by the benchmarks."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any


def per_call_us(function: Callable[[], Any], count: int, *, repeats: int = 3) -> float:
    """Mean µs per call of `function`, the best of `repeats` runs of `count` calls (the machine is shared)."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(count):
            function()
        best = min(best, (time.perf_counter() - start) / count * 1e6)
    return best
