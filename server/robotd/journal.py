"""The append-only journal of one run: its telemetry records and events, written by the daemon's
recorder at least every 100 ms, before the database sees them. A web crash then loses nothing, a
daemon crash at most the last write interval; the next daemon start replays what the database lacks.

`run-<id>/telemetry.bin` holds raw `TELEMETRY_DTYPE` records back to back (`dtype.json` names the
layout), `run-<id>/events.jsonl` one event per line. Both are written with `os.write` on an
`O_APPEND` descriptor, so a write survives the writer's death once it returns.
"""

from __future__ import annotations

import contextlib
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
        self._telemetry = os.open(self.directory / "telemetry.bin", flags, 0o600)
        self._events = os.open(self.directory / "events.jsonl", flags, 0o600)

    def append_telemetry(self, records: np.ndarray) -> None:
        if len(records):
            os.write(self._telemetry, records.tobytes())

    def append_events(self, events: list[dict[str, Any]]) -> None:
        if events:
            os.write(self._events, "".join(json.dumps(to_jsonable(e)) + "\n" for e in events).encode())

    def close(self) -> None:
        for descriptor in (self._telemetry, self._events):
            with contextlib.suppress(OSError):
                os.close(descriptor)

    def remove(self) -> None:
        """Once the database holds everything of the run."""
        self.close()
        shutil.rmtree(self.directory, ignore_errors=True)


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


def remove_journal(journal_dir: Path, run_id: int) -> None:
    shutil.rmtree(run_directory(journal_dir, run_id), ignore_errors=True)


def _tuples(descr: Any) -> Any:
    """JSON turned the dtype description's tuples into lists; numpy wants them back."""
    if isinstance(descr, list):
        return [tuple(_tuples(part) for part in field) if isinstance(field, list) else field for field in descr]
    return descr
