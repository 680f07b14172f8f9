"""The export process (issue 20 Build 7): `run_export_process`, one process per export job, forked from a
forkserver that has imported this module (`server.exports.jobs.start_export_process`).

The web process only moves bytes: its feeder thread sends the job and each run's header and stored telemetry
chunks as frames through a pipe; this process spools them to disk (a reader thread, so the feeder never
waits on the encoding), encodes the export batch by batch and writes it to `<job dir>/output`, which the web
process streams to the client while it grows. Progress goes to `<job dir>/progress.json`.

Frames: one message each, a kind byte then the payload. `J` the job (JSON), `R` a run's header (JSON:
metadata, events), `C` one telemetry chunk (`.npy`), `E` the run's end, `Z` the job's end.
"""

from __future__ import annotations

import io
import json
import queue
import resource
import sys
import threading
import time
import traceback
from collections.abc import Iterator
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any, BinaryIO, cast

import numpy as np

from server.exports.bundle import write_bundle
from server.exports.dataset import write_dataset_zip
from server.exports.formats import EXPORT_FORMATS, check_format
from server.exports.log import SessionLog, SessionLogError
from server.exports.stream import ForwardSink, LogStream, RecordSpool, clocked_events

OUTPUT_FILE = "output"
PROGRESS_FILE = "progress.json"
PROGRESS_PERIOD_S = 0.2
SPOOL_AHEAD_RUNS = 2  # runs spooled ahead of the one being encoded


def write_frame(channel: Connection, kind: bytes, payload: bytes) -> None:
    channel.send_bytes(kind + payload)


def read_frame(channel: Connection) -> tuple[bytes, bytes]:
    try:
        message = channel.recv_bytes()
    except EOFError as error:
        raise EOFError("the web process closed the export's input before its end") from error
    return message[:1], message[1:]


class Progress:
    """`progress.json`, replaced atomically: state, samples encoded, fraction, bytes written, error."""

    def __init__(self, directory: Path, total_samples: int) -> None:
        self.path = directory / PROGRESS_FILE
        self.total_samples = max(1, total_samples)
        self.passes = 1  # passes over each run's telemetry (JSON writes one per field)
        self.samples_done = 0
        self.sink: ForwardSink | None = None
        self._written_at = 0.0
        self.write("running")

    def add(self, samples: int) -> None:
        self.samples_done += samples
        if time.monotonic() - self._written_at >= PROGRESS_PERIOD_S:
            self.write("running")

    def write(self, state: str, **extra: Any) -> None:
        fraction = 1.0 if state == "done" else min(0.99, self.samples_done / (self.total_samples * self.passes))
        usage = resource.getrusage(resource.RUSAGE_SELF)
        document = {
            "state": state,
            "fraction": fraction,
            "bytes": self.sink.written if self.sink is not None else 0,
            "peak_rss_kb": usage.ru_maxrss,
            "cpu_s": usage.ru_utime + usage.ru_stime,
            **extra,
        }
        temporary = self.path.with_suffix(".tmp")
        temporary.write_text(json.dumps(document))
        temporary.replace(self.path)
        self._written_at = time.monotonic()


def spool_runs(stream: Connection, directory: Path, runs: queue.Queue[Any]) -> None:
    """Reader thread: each run's frames into a spool file, then (header, spool) onto `runs`; None at the end."""
    try:
        number = 0
        while True:
            kind, payload = read_frame(stream)
            if kind == b"Z":
                runs.put(None)
                return
            if kind != b"R":
                raise ValueError(f"export frame {kind!r}: expected a run header")
            header = json.loads(payload)
            spool = RecordSpool(directory / f"run-{number}.records")
            number += 1
            while (frame := read_frame(stream))[0] == b"C":
                spool.append(np.load(io.BytesIO(frame[1]), allow_pickle=False))
            if frame[0] != b"E":
                raise ValueError(f"export frame {frame[0]!r}: expected a chunk or the run's end")
            runs.put((header, spool))
    except BaseException as error:  # handed to the encoding thread, which reports it
        runs.put(error)


def passes_over_telemetry(job: dict[str, Any], head: SessionLog) -> int:
    """How often the job's writers read each run (for the progress fraction): JSON once per field."""
    formats = (
        [job["format"]]
        if job["kind"] == "session"
        else ["parquet"]
        if job["layout"] == "parquet_dataset"
        else list(EXPORT_FORMATS)
    )
    return sum(len(head.field_order()) if fmt == "json" else 1 for fmt in formats)


def run_logs(job: dict[str, Any], runs: queue.Queue[Any], progress: Progress) -> Iterator[LogStream]:
    """The spooled runs as `LogStream`s, each spool removed once written."""
    while (item := runs.get()) is not None:
        if isinstance(item, BaseException):
            raise item
        header, spool = item
        try:
            records = spool.mapped()
            events, unplaced = clocked_events(header["events"], records)
            metadata = header["metadata"]
            if unplaced:
                metadata["events_without_tick"] = unplaced
            log = LogStream(records, events, metadata, on_batch=progress.add)
            progress.passes = passes_over_telemetry(job, log.head)
            yield log
        finally:
            spool.remove()


def export(job: dict[str, Any], runs: queue.Queue[Any], progress: Progress, forward: ForwardSink) -> None:
    logs = run_logs(job, runs, progress)
    sink = cast(BinaryIO, forward)  # a write-only file: what zipfile, pyarrow and the writers use of one
    if job["kind"] == "session":
        writer, _, _ = check_format(job["format"])
        for log in logs:  # one run
            writer(log, sink)
    elif job["layout"] == "parquet_dataset":
        write_dataset_zip(logs, sink, selection=job["selection"])
    else:
        write_bundle(logs, sink, selection=job["selection"])


def run_export_process(channel: Connection) -> None:
    """The export process's body: read the job, export it, say how it went in its progress file. Below the
    console's priority: an export never takes the CPU from the robot daemon or the stop listener."""
    from server.realtime.scheduling import lower_priority

    lower_priority("the export process")
    sys.exit(export_job(channel))


def export_job(channel: Connection) -> int:
    kind, payload = read_frame(channel)
    if kind != b"J":
        raise ValueError(f"export frame {kind!r}: expected the job first")
    job = json.loads(payload)
    directory = Path(job["directory"])
    progress = Progress(directory, int(job["total_samples"]))
    runs: queue.Queue[Any] = queue.Queue(maxsize=SPOOL_AHEAD_RUNS)
    threading.Thread(target=spool_runs, args=(channel, directory, runs), name="export-spool", daemon=True).start()
    try:
        with (directory / OUTPUT_FILE).open("wb") as output:
            progress.sink = ForwardSink(output)
            export(job, runs, progress, progress.sink)
    except SessionLogError as error:
        progress.write("failed", error=str(error), field=error.field)
        return 2
    except Exception as error:  # reported to the web process, which shows it
        traceback.print_exc()
        detail = getattr(error, "detail", None) or str(error)
        progress.write("failed", error=f"{detail}", field=getattr(error, "field", None))
        return 1
    progress.write("done")
    return 0
