"""A run read in batches (issue 20 Build 7): its telemetry spooled to a file and mapped, so an export holds
one batch, never the whole run, whatever the format (C3D excepted: ezc3d holds the file, docs/exports.md).

The export process receives a run's stored telemetry chunks one by one and appends their records to a spool
file (`RecordSpool`); `LogStream` maps that file and hands the writers `SessionLog` batches. `ForwardSink`
is the output: a file that refuses to seek, so zipfile streams (data descriptors instead of rewritten
headers) and the web process can send the bytes while the file is still growing.
"""

from __future__ import annotations

import datetime as dt
import io
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from server.exports.log import TIMING_FLAGS, SessionLog, SessionLogError, timing_flags

BATCH_SAMPLES = 20_000  # ~12 MB of telemetry records at 1 kHz: 20 s of a run


class RecordSpool:
    """Telemetry records appended to a file as they arrive, then mapped read-only."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.dtype: np.dtype | None = None
        self._file: BinaryIO | None = path.open("wb")

    def append(self, records: np.ndarray) -> None:
        if self.dtype is None:
            self.dtype = records.dtype
        elif records.dtype != self.dtype:
            raise SessionLogError("telemetry", str(records.dtype), f"every chunk of one run in {self.dtype}")
        assert self._file is not None
        self._file.write(np.ascontiguousarray(records).tobytes())

    def mapped(self) -> np.ndarray:
        """The records written, mapped from the file (pages are read as batches need them)."""
        if self._file is not None:
            self._file.close()
            self._file = None
        if self.dtype is None or self.path.stat().st_size == 0:
            raise SessionLogError("telemetry", 0, "at least one recorded sample")
        return np.memmap(self.path, dtype=self.dtype, mode="r")

    def remove(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None
        self.path.unlink(missing_ok=True)


def clocked_events(
    events: list[dict[str, Any]], telemetry: np.ndarray
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Events (`server.sessions.logs.event_record`) placed on the tick clock of the run's telemetry records,
    and those that cannot be.

    Console commands recorded while the worker's clock was unknown get the tick of the telemetry sample
    nearest to their UTC time (flagged `tick_from_utc`)."""
    placed, unplaced = [], []
    utc_s = telemetry["utc_s"] if "utc_s" in (telemetry.dtype.names or ()) else None
    for event in events:
        record = {**event, "details": dict(event["details"])}
        if record["tick"] is None or record["tick_time_s"] is None:
            if utc_s is None or not len(utc_s):
                unplaced.append(record)
                continue
            utc = dt.datetime.fromisoformat(record["utc"]).timestamp()
            index = int(np.clip(np.searchsorted(utc_s, utc), 0, len(utc_s) - 1))
            record.update(tick=int(telemetry["tick"][index]), tick_time_s=float(telemetry["time_s"][index]))
            record["details"]["tick_from_utc"] = True
        placed.append(record)
    return placed, unplaced


@dataclass
class LogStream:
    """A `RecordedLog` over mapped telemetry records: `batches()` yields `SessionLog`s of `batch_samples`."""

    records: np.ndarray
    events: list[dict[str, Any]]
    metadata: dict[str, Any]
    batch_samples: int = BATCH_SAMPLES
    on_batch: Callable[[int], None] | None = None  # told the samples of each batch written (progress)
    head: SessionLog = field(init=False)

    def __post_init__(self) -> None:
        if self.records.dtype.names is None or not len(self.records):
            raise SessionLogError("telemetry", str(self.records.dtype), "structured records, at least one")
        # The layout, the metadata and the events are checked once, on the first sample.
        self.head = SessionLog.from_telemetry(np.array(self.records[:1]), self.events, self.metadata)
        self.events, self.metadata = self.head.events, self.head.metadata

    @property
    def session_id(self) -> str:
        return self.head.session_id

    @property
    def sample_rate_hz(self) -> float:
        return self.head.sample_rate_hz

    @property
    def sample_count(self) -> int:
        return len(self.records)

    @property
    def first_tick(self) -> int:
        return int(self.records["tick"][0])

    @property
    def duration_s(self) -> float:
        return float(self.records["time_s"][-1] - self.records["time_s"][0])

    def batches(self) -> Iterator[SessionLog]:
        for start in range(0, len(self.records), self.batch_samples):
            chunk = np.array(self.records[start : start + self.batch_samples])
            previous = int(self.records["tick"][start - 1]) if start else None
            columns = {name: chunk[name] for name in chunk.dtype.names or ()}
            yield SessionLog(columns=columns, metadata=self.metadata, previous_tick=previous)
            if self.on_batch is not None:
                self.on_batch(len(chunk))

    def column_batches(self, name: str) -> Iterator[np.ndarray]:
        """One field's values, batch by batch, read from the mapped records without the other fields."""
        derived = name in TIMING_FLAGS and name not in (self.records.dtype.names or ())
        sources = [n for n in ("tick", "skipped_ticks", "lateness_us") if n in (self.records.dtype.names or ())]
        for start in range(0, len(self.records), self.batch_samples):
            stop = start + self.batch_samples
            if derived:
                previous = int(self.records["tick"][start - 1]) if start else None
                columns: dict[str, np.ndarray] = {s: np.array(self.records[s][start:stop]) for s in sources}
                values = timing_flags(columns, previous)[name]
            else:
                values = np.array(self.records[name][start:stop])
            yield values
            if self.on_batch is not None:
                self.on_batch(len(values))

    def whole(self) -> SessionLog:
        log = SessionLog.from_telemetry(np.array(self.records), self.events, self.metadata)
        if self.on_batch is not None:
            self.on_batch(self.sample_count)
        return log


class ForwardSink(io.RawIOBase):
    """Write-only, forward-only output over a file: no `seek` or `tell`, so zipfile writes a streamable zip.
    Counts the bytes written and flushes each write, so a reader of the file sees them at once."""

    def __init__(self, target: BinaryIO) -> None:
        self.target = target
        self.written = 0

    def writable(self) -> bool:
        return True

    def write(self, data: Any) -> int:
        view = memoryview(data).cast("B")
        self.target.write(view)
        self.target.flush()
        self.written += len(view)
        return len(view)
