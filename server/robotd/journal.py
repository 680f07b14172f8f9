"""The append-only journal of one run: its telemetry records and events, written by the daemon's
recorder at least every 100 ms, before the database sees them. A web crash then loses nothing, a
daemon crash at most the last write interval; the next daemon start replays what the database lacks.

`run-<id>/telemetry.bin` holds raw `TELEMETRY_DTYPE` records back to back (`dtype.json` names the
layout), `run-<id>/events.jsonl` one event per line, `run-<id>/decisions.jsonl` the daemon's own
decisions (pause, resume, the end) in the order it took them, before the database hears of them. All
are written with `os.write` on an `O_APPEND` descriptor, so a write survives the writer's death once it
returns. A write that fails (disk full, I/O error) is cut back off the file, so the journal stays a
clean prefix of the run, and raises `OSError` naming the file.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from server.file_modes import private_directory
from server.jsonable import to_jsonable


def run_directory(journal_dir: Path, run_id: int) -> Path:
    return journal_dir / f"run-{run_id}"


class RunJournal:
    """The writer side, for one run."""

    def __init__(self, journal_dir: Path, run_id: int, dtype: np.dtype) -> None:
        self.directory = run_directory(journal_dir, run_id)
        private_directory(self.directory)
        (self.directory / "dtype.json").write_text(json.dumps(np.lib.format.dtype_to_descr(dtype)))
        flags = os.O_WRONLY | os.O_CREAT | os.O_APPEND
        self.telemetry_path, self.events_path = self.directory / "telemetry.bin", self.directory / "events.jsonl"
        self.decisions_path = self.directory / "decisions.jsonl"
        self._telemetry = os.open(self.telemetry_path, flags, 0o600)
        self._events = os.open(self.events_path, flags, 0o600)
        self._decisions = os.open(self.decisions_path, flags, 0o600)

    def append_telemetry(self, records: np.ndarray) -> None:
        if len(records):
            _append(self._telemetry, self.telemetry_path, records.tobytes())

    def append_events(self, events: list[dict[str, Any]]) -> None:
        if events:
            text = "".join(json.dumps(to_jsonable(e)) + "\n" for e in events)
            _append(self._events, self.events_path, text.encode())

    def append_decision(self, decision: dict[str, Any]) -> None:
        _append(self._decisions, self.decisions_path, (json.dumps(to_jsonable(decision), default=str) + "\n").encode())

    def close(self) -> None:
        for descriptor in (self._telemetry, self._events, self._decisions):
            with contextlib.suppress(OSError):
                os.close(descriptor)

    def remove(self) -> None:
        """Once the database holds everything of the run."""
        self.close()
        shutil.rmtree(self.directory, ignore_errors=True)


def _append(descriptor: int, path: Path, data: bytes) -> None:
    """All of `data` at the end of the file, or nothing of it and an `OSError` naming the file."""
    size = os.lseek(descriptor, 0, os.SEEK_END)
    view = memoryview(data)
    try:
        while view:
            written = os.write(descriptor, view)
            if written == 0:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
            view = view[written:]
    except OSError as error:
        with contextlib.suppress(OSError):
            os.ftruncate(descriptor, size)  # a torn record would misalign every later one
        raise OSError(error.errno, error.strerror, str(path)) from error


def journal_counts(journal_dir: Path, run_id: int) -> tuple[int, int]:
    """(telemetry records, events) a run's journal holds, without reading it all."""
    directory = run_directory(journal_dir, run_id)
    records = events = 0
    with contextlib.suppress(OSError, ValueError):
        dtype = np.dtype(np.lib.format.descr_to_dtype(_tuples(json.loads((directory / "dtype.json").read_text()))))
        records = (directory / "telemetry.bin").stat().st_size // dtype.itemsize
    with contextlib.suppress(OSError), (directory / "events.jsonl").open("rb") as handle:
        events = sum(1 for line in handle if line.strip())
    return records, events


def read_journal(journal_dir: Path, run_id: int) -> tuple[np.ndarray | None, list[dict[str, Any]]]:
    """What a journal holds: (telemetry records or None, events). A torn last record or line is dropped."""
    directory = run_directory(journal_dir, run_id)
    records = None
    with contextlib.suppress(OSError, ValueError):
        dtype = np.dtype(np.lib.format.descr_to_dtype(_tuples(json.loads((directory / "dtype.json").read_text()))))
        raw = (directory / "telemetry.bin").read_bytes()
        records = np.frombuffer(raw[: len(raw) - len(raw) % dtype.itemsize], dtype=dtype).copy()
    events = []
    with contextlib.suppress(OSError):
        for line in (directory / "events.jsonl").read_text().splitlines():
            with contextlib.suppress(ValueError):
                events.append(json.loads(line))
    return records, events


def read_decisions(journal_dir: Path, run_id: int) -> list[dict[str, Any]]:
    """The daemon's journalled decisions of a run, oldest first (a torn last line is dropped)."""
    decisions = []
    with contextlib.suppress(OSError):
        for line in (run_directory(journal_dir, run_id) / "decisions.jsonl").read_text().splitlines():
            with contextlib.suppress(ValueError):
                decisions.append(json.loads(line))
    return decisions


def remove_journal(journal_dir: Path, run_id: int) -> None:
    shutil.rmtree(run_directory(journal_dir, run_id), ignore_errors=True)


def _tuples(descr: Any) -> Any:
    """JSON turned the dtype description's tuples into lists; numpy wants them back."""
    if isinstance(descr, list):
        return [tuple(_tuples(part) for part in field) if isinstance(field, list) else field for field in descr]
    return descr
