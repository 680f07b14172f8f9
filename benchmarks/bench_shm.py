"""Cost of the fenced seqlock (issue 12 §6): one write per worker tick, one read per telemetry poll.

The baseline, measured in the same run on the same block, is the seqlock write as it was before the
memory barriers: numpy updates of the sequence around a structured numpy copy, nothing between (correct
only on x86-64's TSO). The fenced write is one compiled call: sequence, barrier, byte copy, barrier,
sequence. Target: the fenced write costs at most 2 µs, 0.2 % of a 1 kHz tick.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from benchmarks.timing import per_call_us
from server.realtime.shm import Seqlock
from server.realtime.telemetry import TELEMETRY_DTYPE

WRITE_TARGET_US = 2.0


def _unfenced_writer(seqlock: Seqlock) -> Any:
    """The write as it was: numpy updates of the sequence around a structured copy, no barrier."""
    sequence = np.ndarray((1,), np.uint64, seqlock.block.buffer, 0)
    target = np.ndarray((1,), seqlock.dtype, seqlock.block.buffer, 64)

    def write(record: np.ndarray) -> None:
        sequence[0] += np.uint64(1)
        target[:] = record
        sequence[0] += np.uint64(1)

    return write


def _unfenced_reader(seqlock: Seqlock) -> Any:
    """The read as it was: sequence, structured copy, sequence, and a structured copy out."""
    sequence = np.ndarray((1,), np.uint64, seqlock.block.buffer, 0)
    source = np.ndarray((1,), seqlock.dtype, seqlock.block.buffer, 64)
    scratch = np.zeros(1, seqlock.dtype)

    def read() -> np.ndarray:
        while True:
            before = int(sequence[0])
            if not before & 1:
                scratch[:] = source
                if int(sequence[0]) == before:
                    return scratch.copy()

    return read


def run(*, quick: bool) -> dict[str, Any]:
    count = 20_000 if quick else 200_000
    seqlock = Seqlock(TELEMETRY_DTYPE)
    record = np.zeros(1, TELEMETRY_DTYPE)
    try:
        unfenced = _unfenced_writer(seqlock)
        baseline_write_us = per_call_us(lambda: unfenced(record), count, repeats=5)
        write_us = per_call_us(lambda: seqlock.write(record), count, repeats=5)
        read_us = per_call_us(seqlock.read, count, repeats=5)
        baseline_read_us = per_call_us(_unfenced_reader(seqlock), count, repeats=5)
    finally:
        seqlock.close()
    return {
        "record_bytes": TELEMETRY_DTYPE.itemsize,
        "write_us": round(write_us, 3),
        "write_target_us": WRITE_TARGET_US,
        "write_met": write_us <= WRITE_TARGET_US,
        "baseline_unfenced_write_us": round(baseline_write_us, 3),
        "fenced_over_baseline": round(write_us / baseline_write_us, 3),
        "read_us": round(read_us, 3),
        "baseline_unfenced_read_us": round(baseline_read_us, 3),
    }
