"""Recorded traces onto a uniform time grid: the tick's time stamps jitter, and a late tick or a lost sample
must not bend a filter that assumes one sample interval."""

from __future__ import annotations

import numpy as np


def on_uniform_grid(time_s: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """The grid (N',) at the median sample interval from the first stamp to the last, that interval (s), and
    each column of `values` (N, K) linearly interpolated onto the grid (N', K)."""
    time_s = np.asarray(time_s, dtype=float)
    values = np.asarray(values, dtype=float)
    period_s = float(np.median(np.diff(time_s)))
    grid_s = time_s[0] + period_s * np.arange(round((time_s[-1] - time_s[0]) / period_s) + 1)
    on_grid = np.column_stack([np.interp(grid_s, time_s, values[:, column]) for column in range(values.shape[1])])
    return grid_s, period_s, on_grid
