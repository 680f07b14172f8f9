"""The audit journal: audited reads are recorded off the request path and never lost.

A read appends one JSON line to this process's journal file and returns only once the line is on disk
(`fdatasync`; concurrent readers share one sync: group commit). A background thread drains the journal
into `audit_log` in batches, a few times per second. So a crash at any point after the read has not
lost its record: a line on disk is either already in the database, or is drained by the next process
that starts (or by a sibling process: a file whose owner died is no longer `flock`ed).

Every line carries a unique `journal_id`, stored with the row, so a line drained twice (a crash between
the database commit and the removal of the file) is inserted once. A torn last line (a crash in the
middle of `write`) was never synced, so its request never answered: it is skipped.

Files, in `<data_dir>/audit-journal/`: `<uuid>.active.jsonl` (being appended to, locked by its process)
and `<uuid>.draining.jsonl` (rotated out, being drained). Both kinds are drained at start-up.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import fcntl
import json
import logging
import os
import threading
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sqlalchemy import insert, select

from server.audit.models import AuditEntry
from server.db import Database, write_transaction
from server.file_modes import private_directory

logger = logging.getLogger(__name__)

INSERT_BATCH = 500


def _fsync_directory(directory: Path) -> None:
    descriptor = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(descriptor)
    finally:
        os.close(descriptor)


def _locked_descriptor(path: Path, flags: int) -> int | None:
    """An open descriptor holding the file's exclusive lock, or None if another process holds it."""
    try:
        descriptor = os.open(path, flags, 0o600)
    except FileNotFoundError:
        return None
    try:
        fcntl.flock(descriptor, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(descriptor)
        return None
    return descriptor


@dataclass
class _Rotated:
    path: Path
    descriptor: int  # kept open, so that the lock holds until the file is drained


class AuditJournal:
    def __init__(self, directory: Path, *, drain_interval_s: float = 0.25) -> None:
        self.directory = directory
        self.drain_interval_s = drain_interval_s
        self._append_lock = threading.Lock()  # order: _sync_lock before _append_lock
        self._sync_lock = threading.Lock()
        self._drain_lock = threading.Lock()
        self._written = 0
        self._synced = 0
        self._rotated_written = 0
        self._active_path: Path | None = None
        self._descriptor: int | None = None
        self._rotated: list[_Rotated] = []
        self._database: Database | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # --- the request path ------------------------------------------------------------------------

    def append(
        self,
        *,
        user_id: int | None,
        action: str,
        resource_type: str,
        resource_id: int | None = None,
        details: dict[str, Any] | None = None,
    ) -> None:
        """Durably journal one audit entry; returns once it is on disk."""
        entry = {
            "journal_id": uuid.uuid4().hex,
            "utc": dt.datetime.now(dt.UTC).isoformat(),
            "user_id": user_id,
            "action": action,
            "resource_type": resource_type,
            "resource_id": resource_id,
            "details": details or {},
        }
        line = (json.dumps(entry, separators=(",", ":")) + "\n").encode()
        with self._append_lock:
            if self._descriptor is None:
                raise RuntimeError("the audit journal is closed")
            os.write(self._descriptor, line)  # O_APPEND: one write per line, never interleaved
            self._written += 1
            sequence = self._written
        self._sync(sequence)

    def _sync(self, sequence: int) -> None:
        with self._sync_lock:
            if self._synced >= sequence:
                return  # another request's sync covered this line
            with self._append_lock:
                target, descriptor = self._written, self._descriptor
            assert descriptor is not None
            os.fdatasync(descriptor)
            self._synced = target

    # --- lifecycle -------------------------------------------------------------------------------

    def open(self, database: Database) -> None:
        """Start journaling into a fresh file, replay what earlier processes left, start the drainer."""
        private_directory(self.directory)
        self._database = database
        self._open_active()
        self.drain()
        self._stop.clear()
        self._thread = threading.Thread(target=self._drain_forever, name="audit-journal-drain", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop the drainer and drain everything; whatever cannot be drained stays on disk for next time."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30.0)
        try:
            self.drain()
        except Exception:
            logger.exception("audit journal: final drain failed; the entries stay in %s", self.directory)
        with self._sync_lock, self._append_lock:
            if self._descriptor is not None:
                os.close(self._descriptor)
                self._descriptor = None
            if self._active_path is not None and self._written == self._rotated_written:
                self._active_path.unlink(missing_ok=True)  # empty: nothing to keep
        for rotated in self._rotated:
            os.close(rotated.descriptor)
        self._rotated = []

    def _open_active(self) -> None:
        path = self.directory / f"{uuid.uuid4().hex}.active.jsonl"
        descriptor = _locked_descriptor(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
        assert descriptor is not None  # a fresh name: nobody else holds it
        _fsync_directory(self.directory)
        self._active_path, self._descriptor = path, descriptor

    def _rotate(self) -> None:
        """Hand the active file to the drainer (still locked by us) and continue in a fresh one."""
        with self._sync_lock, self._append_lock:
            if self._written == self._rotated_written or self._descriptor is None:
                return
            assert self._active_path is not None
            os.fdatasync(self._descriptor)
            self._synced = self._written
            draining = self._active_path.with_name(self._active_path.name.replace(".active.", ".draining."))
            self._active_path.rename(draining)
            self._rotated.append(_Rotated(draining, self._descriptor))
            self._rotated_written = self._written
            self._open_active()

    # --- draining --------------------------------------------------------------------------------

    def _drain_forever(self) -> None:
        while not self._stop.wait(self.drain_interval_s):
            try:
                self.drain()
            except Exception:  # the database may be away for a while: the entries wait on disk
                logger.exception("audit journal: drain failed; retrying")

    def drain(self) -> int:
        """Move every journaled entry into the database now; returns the number of new rows."""
        assert self._database is not None
        with self._database.exclusive(), self._drain_lock:
            self._rotate()
            inserted = 0
            for rotated in list(self._rotated):
                inserted += self._drain_file(rotated.path)
                self._rotated.remove(rotated)
                os.close(rotated.descriptor)
            for path in sorted(self.directory.glob("*.jsonl")):
                if path == self._active_path:
                    continue
                descriptor = _locked_descriptor(path, os.O_RDONLY)
                if descriptor is None:
                    continue  # a live process's file: it drains it itself
                try:
                    inserted += self._drain_file(path)
                    logger.info("audit journal: replayed %s left by an earlier process", path.name)
                finally:
                    os.close(descriptor)
            return inserted

    def _drain_file(self, path: Path) -> int:
        entries = []
        for line in path.read_bytes().split(b"\n"):
            with contextlib.suppress(ValueError):  # a torn last line was never synced, nor answered
                entries.append(json.loads(line))
        inserted = self._insert(entries)
        path.unlink()
        _fsync_directory(self.directory)
        return inserted

    def _insert(self, entries: list[dict[str, Any]]) -> int:
        assert self._database is not None
        inserted = 0
        for first in range(0, len(entries), INSERT_BATCH):
            batch = {entry["journal_id"]: entry for entry in entries[first : first + INSERT_BATCH]}
            with self._database.session() as session, write_transaction(session):
                seen = set(session.scalars(select(AuditEntry.journal_id).where(AuditEntry.journal_id.in_(batch))))
                rows = [
                    {
                        "journal_id": journal_id,
                        "utc": dt.datetime.fromisoformat(entry["utc"]),
                        "user_id": entry["user_id"],
                        "action": entry["action"],
                        "resource_type": entry["resource_type"],
                        "resource_id": entry["resource_id"],
                        "details": entry["details"],
                    }
                    for journal_id, entry in batch.items()
                    if journal_id not in seen
                ]
                if rows:  # one executemany: the drain costs the web process as little CPU as it can
                    session.execute(insert(AuditEntry), rows)
                inserted += len(rows)
        return inserted
