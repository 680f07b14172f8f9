"""The robot daemon's recorder: where a run's records go. Telemetry and events go first into the run's
append-only journal on the data disk (server.robotd.journal: it survives any crash of the web side or of
the database), then to the database through the daemon's one writer (server.robotd.writer), telemetry in
chunks of about a second. A run's journal goes only once the database holds at least what it holds.

A journal write that fails (disk full, I/O error) is noted here (`failure`, in words, for the daemon's
status and /health); what to do about it, a controlled stop, is the run controller's (server.robotd.daemon).
Starts are refused until a probe write succeeds again.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import errno
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.db import Database, write_transaction
from server.errors import ConflictError
from server.realtime.telemetry import TELEMETRY_DTYPE
from server.robotd.journal import RunJournal, journal_counts
from server.robotd.models import RunOutcome, RunState, SessionEvent, SessionRun, TelemetryChunk
from server.robotd.records import encode_chunk, event_row
from server.robotd.writer import DatabaseWriter

log = logging.getLogger("ssp_rehab.robotd")

CHUNK_PERIOD_S = 1.0  # telemetry reaches the database in chunks of about a second
RECORDING_PROBE_PERIOD_S = 1.0  # while the recorder cannot write, try a probe write this often
RECORDING_PROBE_BYTES = TELEMETRY_DTYPE.itemsize * 1000  # a second of telemetry at 1 kHz must fit


@dataclass
class ActiveRun:
    run_id: int
    session_id: int
    controller: str | None  # the link of the console that started it (None: in-process)
    journal: RunJournal | None
    state: RunState = RunState.RUNNING
    pending: list[np.ndarray] = field(default_factory=list)
    sequence: int = 0
    last_chunk_s: float = field(default_factory=time.monotonic)
    outcome: RunOutcome | None = None
    tail_deadline: float | None = None
    journal_failed: bool = False  # a write failed: the rest of the run is held in memory for the database
    # The run as the daemon knows it: what stop and pause answer with, never waiting for the database.
    version_id: int | None = None
    started_by_id: int | None = None
    started_at: dt.datetime = field(default_factory=lambda: dt.datetime.now(dt.UTC))
    ended_at: dt.datetime | None = None
    stopped_by_id: int | None = None
    sample_count: int = 0

    def record(self, robot: str) -> dict[str, Any]:
        """The run as the daemon knows it, in the shape of `SessionRunOut`."""
        return {
            "id": self.run_id,
            "scheduled_session_id": self.session_id,
            "prescription_version_id": self.version_id,
            "robot": robot,
            "state": self.state.value,
            "outcome": self.outcome.value if self.outcome is not None else None,
            "started_at": self.started_at.isoformat(),
            "ended_at": self.ended_at.isoformat() if self.ended_at is not None else None,
            "started_by_id": self.started_by_id,
            "stopped_by_id": self.stopped_by_id,
            "sample_count": self.sample_count,
        }


class RunRecorder:
    """The journal and the database side of recording, for one robot's runs."""

    def __init__(self, robot: str, database: Database, journal_dir: Path | None, chunk_period_s: float) -> None:
        self.robot = robot
        self.journal_dir = journal_dir
        self.chunk_period_s = chunk_period_s
        self.writer = DatabaseWriter(database)
        self.failure: str | None = None  # why the recorder cannot write, in words (None: it can)
        self._next_probe_s = 0.0

    def start(self) -> None:
        self.writer.start()

    def stop(self) -> None:
        """Once everything queued is written (retried while the database is away)."""
        self.writer.drain()
        self.writer.stop()

    # --- the journal --------------------------------------------------------------------------------

    def open_journal(self, run_id: int) -> tuple[RunJournal | None, OSError | None]:
        """The new run's journal, or the error that kept it from being made (with the path it names)."""
        if self.journal_dir is None:
            return None, None
        try:
            return RunJournal(self.journal_dir, run_id, TELEMETRY_DTYPE), None
        except OSError as error:
            return None, error if error.filename else OSError(error.errno, error.strerror, str(self.journal_dir))

    def journal(self, run: ActiveRun, write: Callable[[RunJournal], None]) -> OSError | None:
        """Write into the run's journal; the error when it failed (the run holds the rest in memory after)."""
        if run.journal is None or run.journal_failed:
            return None
        try:
            write(run.journal)
        except OSError as error:
            run.journal_failed = True  # nothing more goes to this journal
            return error
        return None

    def take(self, run: ActiveRun, telemetry: np.ndarray | None, events: list[dict[str, Any]]) -> OSError | None:
        """Into memory and the journal (survives any crash of the web side), then on to the database; the
        journal's error, if a write failed."""
        failed = None
        if telemetry is not None and len(telemetry):
            records = np.array(telemetry, copy=True)
            run.pending.append(records)
            run.sample_count += len(records)
            failed = self.journal(run, lambda journal: journal.append_telemetry(records))
        if events:
            self.store_events(run.run_id, events)
            failed = failed or self.journal(run, lambda journal: journal.append_events(events))
        return failed

    def note_failure(self, run: ActiveRun, error: OSError) -> dict[str, Any]:
        """The run's journal cannot be written: say so (`failure`) and keep what follows in memory until the
        database takes it; the details of the `recording_failed` event."""
        run.journal_failed = True
        name = errno.errorcode.get(error.errno or 0, str(error.errno))
        self.failure = (
            f"the recorder cannot write {error.filename}: [Errno {error.errno}] {error.strerror} ({name}); "
            "the run was stopped; free space on the data disk (or repair it) before the next session"
        )
        self._next_probe_s = time.monotonic() + RECORDING_PROBE_PERIOD_S
        log.error("run %d: %s", run.run_id, self.failure)
        return {"errno": error.errno, "error": name, "message": error.strerror, "path": str(error.filename),
                "samples_held_in_memory": int(sum(len(records) for records in run.pending))}  # fmt: skip

    def probe(self) -> bool:
        """Can the recorder write again? (A probe file of a second's telemetry, written and removed.)"""
        if self.journal_dir is None:
            return True
        probe = self.journal_dir / ".write-probe"
        try:
            self.journal_dir.mkdir(parents=True, exist_ok=True)
            descriptor = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
            try:
                written = os.write(descriptor, bytes(RECORDING_PROBE_BYTES))
                os.fsync(descriptor)
            finally:
                os.close(descriptor)
            if written != RECORDING_PROBE_BYTES:
                return False
        except OSError:
            return False
        finally:
            with contextlib.suppress(OSError):
                probe.unlink()
        if self.failure is not None:
            log.warning("the recorder can write again (%s)", self.journal_dir)
        self.failure = None
        return True

    def probe_when_due(self) -> None:
        if self.failure is not None and time.monotonic() >= self._next_probe_s:
            self._next_probe_s = time.monotonic() + RECORDING_PROBE_PERIOD_S
            self.probe()

    def refuse_start_while_failing(self) -> None:
        failure = self.failure
        if failure is not None and not self.probe():
            raise ConflictError(f"robot {self.robot!r} cannot start: {failure}", field="recording")

    # --- the database -------------------------------------------------------------------------------

    def store_events(self, run_id: int | None, events: list[dict[str, Any]]) -> None:
        rows = [event_row(run_id, event) for event in events]

        def write(session: Session) -> None:
            with write_transaction(session):
                session.add_all(rows)

        self.writer.submit(write, retry=True)

    def store_chunk(self, run: ActiveRun) -> None:
        run.last_chunk_s = time.monotonic()
        if not run.pending:
            return
        records = np.concatenate(run.pending)
        run.pending = []
        sequence, run.sequence = run.sequence, run.sequence + 1
        run_id = run.run_id

        def write(session: Session) -> None:
            with write_transaction(session):
                session.add(
                    TelemetryChunk(
                        run_id=run_id,
                        sequence=sequence,
                        first_tick=int(records["tick"][0]),
                        sample_count=len(records),
                        data=encode_chunk(records),
                    )
                )
                stored = session.get(SessionRun, run_id)
                if stored is not None:
                    stored.sample_count += len(records)

        self.writer.submit(write, retry=True)

    def store_chunk_when_due(self, run: ActiveRun) -> None:
        if time.monotonic() - run.last_chunk_s >= self.chunk_period_s:
            self.store_chunk(run)

    def release(self, run: ActiveRun) -> None:
        """The run's recording is complete: its last chunk goes to the database, then its journal away,
        once the database holds at least what the journal holds."""
        self.store_chunk(run)
        journal, journal_dir, run_id = run.journal, self.journal_dir, run.run_id
        if journal is None or journal_dir is None:
            return

        def remove_once_stored(session: Session) -> None:
            journaled_samples, journaled_events = journal_counts(journal_dir, run_id)
            samples = session.scalar(
                select(func.coalesce(func.sum(TelemetryChunk.sample_count), 0)).where(TelemetryChunk.run_id == run_id)
            )
            events = session.scalar(select(func.count()).select_from(SessionEvent).where(SessionEvent.run_id == run_id))
            if int(samples or 0) < journaled_samples or int(events or 0) < journaled_events:
                journal.close()
                log.error(
                    "run %d: the database holds %s samples and %s events, its journal %d and %d: journal kept at %s",
                    run_id, samples, events, journaled_samples, journaled_events, journal.directory,
                )  # fmt: skip
                return
            journal.remove()

        self.writer.submit(remove_once_stored, retry=True)
