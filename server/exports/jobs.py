"""Export jobs of the web process (issue 20 Build 7): each export is built by its own export process
(`start_export_process`, at most `max_running` at once, the rest queued) and streamed from the file it
writes, so neither the event loop nor the request threads encode anything, and no export is held in memory.

A job's feeder thread reads the runs from the database (header, then the stored telemetry chunks, a few at a
time) and sends them to the export process (`server.exports.worker`). `stream_job` yields the output as it
grows; `ExportResponse` answers 409 with the reason when the job fails before its first byte, else 200 and
the bytes. Finished jobs stay for `keep_s` (a later download, the progress endpoint), then are removed.
"""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import json
import logging
import multiprocessing
import multiprocessing.process
import os
import shutil
import sys
import threading
import time
import types
import uuid
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

from starlette.responses import JSONResponse, Response
from starlette.types import Receive, Scope, Send

from server.exports import worker
from server.exports.worker import OUTPUT_FILE, PROGRESS_FILE, write_frame
from server.file_modes import OWNER_ONLY_DIRECTORY, private_directory

logger = logging.getLogger(__name__)

EXPORT_PROCESS_NAME = "ssp-rehab-export"
MAX_RUNNING_EXPORTS = 2  # two cores: more would only slow each other and the console
KEEP_FINISHED_S = 900.0
STREAM_CHUNK_BYTES = 256 * 1024
POLL_S = 0.05
STOP_WAIT_S = 5.0

# feed(send): sends each run as `send(b"R", header json)`, `send(b"C", chunk)`…, `send(b"E", b"")`
Feed = Callable[[Callable[[bytes, bytes], None]], None]


# Export processes fork from a forkserver that has imported the exporters once: a fresh interpreter took 4 s
# (20 s at load 20) to import them; forking the web process itself would copy its threads' locks.
_PROCESSES = multiprocessing.get_context("forkserver")
_PROCESSES.set_forkserver_preload([worker.__name__])


def start_export_process() -> tuple[multiprocessing.process.BaseProcess, Connection]:
    """The one place an export process starts (named `ssp-rehab-export`, niced by its body); returns it and
    the pipe to feed it."""
    receiver, sender = _PROCESSES.Pipe(duplex=False)
    process = _PROCESSES.Process(
        target=worker.run_export_process, args=(receiver,), name=EXPORT_PROCESS_NAME, daemon=True
    )
    with _START_LOCK, _without_main_module():
        process.start()
    receiver.close()
    return process, sender


_START_LOCK = threading.Lock()


@contextlib.contextmanager
def _without_main_module() -> Iterator[None]:
    """multiprocessing makes each child import the parent's `__main__` (under `python -m server.cli.main`,
    the whole console: ~2.5 s of CPU per export at load 20); the export process needs none of it. The main
    module is hidden while the child's start-up data is taken, in this thread, then put back."""
    main = sys.modules["__main__"]
    sys.modules["__main__"] = types.ModuleType("__main__")
    try:
        yield
    finally:
        sys.modules["__main__"] = main


@dataclass
class ExportJob:
    """One export: what it is (`spec`, sent to the export process), who asked, and how it goes."""

    owner_id: int
    spec: dict[str, Any]
    feed: Feed
    filename: str
    media_type: str
    total_samples: int
    description: str
    id: str = field(default_factory=lambda: uuid.uuid4().hex)
    created_utc: dt.datetime = field(default_factory=lambda: dt.datetime.now(dt.UTC))
    directory: Path = Path()
    process: multiprocessing.process.BaseProcess | None = None
    channel: Connection | None = None
    feed_error: str | None = None
    finished_monotonic: float | None = None

    @property
    def output(self) -> Path:
        return self.directory / OUTPUT_FILE

    def progress(self) -> dict[str, Any]:
        try:
            return dict(json.loads((self.directory / PROGRESS_FILE).read_text()))
        except (OSError, ValueError):
            return {}

    def status(self) -> dict[str, Any]:
        """state (queued | running | done | failed), fraction 0–1, bytes written, and why it failed."""
        progress = self.progress()
        base: dict[str, Any] = {"id": self.id, "description": self.description, "filename": self.filename}
        base.update(media_type=self.media_type, total_samples=self.total_samples, created_utc=self.created_utc)
        written = self.output.stat().st_size if self.output.exists() else 0
        if self.process is None:
            return {**base, "state": "queued", "fraction": 0.0, "bytes": 0, "error": None, "field": None}
        code = self.process.exitcode
        state, error = "running", None
        if self.feed_error is not None:
            state, error = "failed", self.feed_error
        elif code is not None:
            if code == 0 and progress.get("state") == "done":
                state = "done"
            else:
                state = "failed"
                error = progress.get("error") or f"the export process ended with exit code {code}"
        fraction = 1.0 if state == "done" else float(progress.get("fraction", 0.0))
        return {**base, "state": state, "fraction": fraction, "bytes": written, "error": error,
                "field": progress.get("field") if state == "failed" else None}  # fmt: skip

    def finished(self) -> bool:
        return self.feed_error is not None or (self.process is not None and self.process.exitcode is not None)


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class ExportJobs:
    """The web process's export jobs, at most `max_running` export processes at once."""

    def __init__(self, base: Path, *, max_running: int = MAX_RUNNING_EXPORTS, keep_s: float = KEEP_FINISHED_S):
        """Jobs live in `base/<pid>/<job id>/`: a web process's own directory, so that several web processes
        can share `base`; directories of processes that are gone are removed."""
        self.root = base / str(os.getpid())
        self.max_running = max_running
        self.keep_s = keep_s
        self._jobs: dict[str, ExportJob] = {}
        self._lock = threading.Lock()
        for directory in base.glob("*") if base.is_dir() else ():
            if not directory.name.isdigit() or not _process_alive(int(directory.name)):
                shutil.rmtree(directory, ignore_errors=True)
        private_directory(self.root)  # exports hold patient data: owner-only, as the database file

    def submit(self, job: ExportJob) -> ExportJob:
        job.directory = self.root / job.id
        job.directory.mkdir(mode=OWNER_ONLY_DIRECTORY)
        with self._lock:
            self._jobs[job.id] = job
        self.refresh()
        return job

    def get(self, job_id: str, owner_id: int) -> ExportJob | None:
        """The job, for the user who asked for it only."""
        self.refresh()
        with self._lock:
            job = self._jobs.get(job_id)
        return job if job is not None and job.owner_id == owner_id else None

    def refresh(self) -> None:
        """Start queued jobs while slots are free; forget jobs finished more than `keep_s` ago."""
        now = time.monotonic()
        with self._lock:
            for job in list(self._jobs.values()):
                if job.finished() and job.finished_monotonic is None:
                    job.finished_monotonic = now
                if job.finished_monotonic is not None and now - job.finished_monotonic > self.keep_s:
                    del self._jobs[job.id]
                    shutil.rmtree(job.directory, ignore_errors=True)
            running = sum(1 for job in self._jobs.values() if job.process is not None and not job.finished())
            for job in self._jobs.values():
                if running >= self.max_running:
                    break
                if job.process is None and job.feed_error is None:
                    self._start(job)
                    running += 1

    def _start(self, job: ExportJob) -> None:
        job.process, job.channel = start_export_process()
        feeder = threading.Thread(target=self._feed, args=(job,), name=f"export-feed-{job.id[:8]}", daemon=True)
        feeder.start()

    def _feed(self, job: ExportJob) -> None:
        assert job.process is not None and job.channel is not None
        channel = job.channel
        try:
            spec = {**job.spec, "directory": str(job.directory), "total_samples": job.total_samples}
            write_frame(channel, b"J", json.dumps(spec).encode())
            job.feed(lambda kind, payload: write_frame(channel, kind, payload))
            write_frame(channel, b"Z", b"")
        except (BrokenPipeError, ConnectionResetError):
            pass  # the export process ended early: its progress file says why
        except Exception as error:  # the database or a refused record: the job fails and says why
            job.feed_error = getattr(error, "detail", None) or str(error)
            job.process.kill()
        finally:
            with contextlib.suppress(OSError):
                channel.close()

    def close(self) -> None:
        """Stop every export process (the web process is shutting down) and remove the jobs' files."""
        with self._lock:
            jobs = list(self._jobs.values())
            self._jobs.clear()
        for job in jobs:
            if job.process is not None and job.process.exitcode is None:
                job.process.terminate()
                job.process.join(STOP_WAIT_S)
                if job.process.exitcode is None:
                    job.process.kill()
                    job.process.join()
        shutil.rmtree(self.root, ignore_errors=True)


class ExportFailedError(RuntimeError):
    """The export failed after its first bytes were sent: the download is cut off; the job says why."""


async def stream_job(jobs: ExportJobs, job: ExportJob) -> AsyncIterator[bytes]:
    """The job's output as it is written, to its end; raises `ExportFailedError` if the job fails."""
    while not job.output.exists():
        if job.finished():
            raise ExportFailedError(job.status()["error"])
        jobs.refresh()
        await asyncio.sleep(POLL_S)
    with job.output.open("rb") as output:
        while True:
            data = output.read(STREAM_CHUNK_BYTES)  # from the page cache: microseconds
            if data:
                yield data
                continue
            if job.finished():
                status = job.status()
                if status["state"] != "done":
                    raise ExportFailedError(status["error"])
                rest = output.read()
                if rest:
                    yield rest
                    continue
                return
            jobs.refresh()
            await asyncio.sleep(POLL_S)


class ExportResponse(Response):
    """Streams a job's output: 409 with the reason if the job fails before its first byte, else 200 with the
    file as it is built (`X-Export-Job` names the job for the progress endpoint)."""

    def __init__(self, jobs: ExportJobs, job: ExportJob, refusal: str) -> None:
        super().__init__(media_type=job.media_type)
        self.jobs, self.job, self.refusal = jobs, job, refusal

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        chunks = stream_job(self.jobs, self.job)
        try:
            first = await anext(chunks, b"")
        except ExportFailedError as error:
            status = self.job.status()
            refused = JSONResponse({"detail": f"{self.refusal}: {error}", "field": status["field"]}, status_code=409)
            await refused(scope, receive, send)
            return
        headers = [
            (b"content-type", self.job.media_type.encode()),
            (b"content-disposition", f'attachment; filename="{self.job.filename}"'.encode()),
            (b"x-export-job", self.job.id.encode()),
        ]
        await send({"type": "http.response.start", "status": 200, "headers": headers})
        await send({"type": "http.response.body", "body": first, "more_body": True})
        async for chunk in chunks:
            await send({"type": "http.response.body", "body": chunk, "more_body": True})
        await send({"type": "http.response.body", "body": b"", "more_body": False})
