"""The run journal under a failing write (issue 20, defect 3): the write raises naming the file, and what
it wrote in part is cut back off, so every later record stays aligned."""

from __future__ import annotations

import errno
import resource
import signal
from pathlib import Path

import numpy as np
import pytest

from server.realtime.telemetry import TELEMETRY_DTYPE
from server.robotd.journal import RunJournal, journal_counts, read_journal


def records(first_tick: int, count: int) -> np.ndarray:
    block = np.zeros(count, TELEMETRY_DTYPE)
    block["tick"] = np.arange(first_tick, first_tick + count)
    return block


def test_a_failed_journal_write_is_cut_back_and_names_the_file(tmp_path: Path) -> None:
    journal = RunJournal(tmp_path, 7, TELEMETRY_DTYPE)
    journal.append_telemetry(records(0, 10))
    size = journal.telemetry_path.stat().st_size
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    previous = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of the signal
    try:
        # Room for one and a half records: the kernel writes part of the block, then refuses the rest.
        resource.setrlimit(resource.RLIMIT_FSIZE, (size + TELEMETRY_DTYPE.itemsize * 3 // 2, hard))
        with pytest.raises(OSError) as raised:
            journal.append_telemetry(records(10, 5))
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, previous)
    assert raised.value.errno == errno.EFBIG and raised.value.filename == str(journal.telemetry_path), raised.value
    assert journal.telemetry_path.stat().st_size == size, "the torn write was left in the journal"
    journal.append_telemetry(records(15, 2))
    journal.append_events([{"kind": "recording_failed", "details": {"errno": errno.EFBIG}}])
    stored, events = read_journal(tmp_path, 7)
    assert stored is not None and stored["tick"].tolist() == [*range(10), 15, 16]
    assert journal_counts(tmp_path, 7) == (12, 1) and events[0]["kind"] == "recording_failed"
