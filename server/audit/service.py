"""Writing and reading the audit log. Details hold ids and field names, never patient data.

Changes: `record` joins the caller's transaction, so a change and its audit entry are committed together
or not at all. Reads: `record_read` appends to the audit journal of the session's database (fsync'd,
drained into the table in the background: `server.audit.journal`), so a read never waits for a database
write; without a journal (the CLI) it writes the entry in its own transaction.
"""

from __future__ import annotations

import threading
from typing import Any

from sqlalchemy import Engine, select
from sqlalchemy.orm import Session

from server.audit.journal import AuditJournal
from server.audit.models import AuditEntry
from server.db import write_transaction

_journals: dict[Engine, AuditJournal] = {}
_journals_lock = threading.Lock()


def use_journal(engine: Engine, journal: AuditJournal | None) -> None:
    """Route the reads audited on `engine`'s sessions through `journal` (None: write them directly)."""
    with _journals_lock:
        if journal is None:
            _journals.pop(engine, None)
        else:
            _journals[engine] = journal


def journal_for(session: Session) -> AuditJournal | None:
    return _journals.get(session.get_bind().engine)


def record_read(
    *,
    session: Session,
    user_id: int | None,
    action: str,
    resource_type: str,
    resource_id: int | None = None,
    details: dict[str, Any] | None = None,
) -> None:
    """Audit a read: durable on return, but off the database's write path."""
    journal = journal_for(session)
    if journal is not None:
        journal.append(
            user_id=user_id, action=action, resource_type=resource_type, resource_id=resource_id, details=details
        )
        return
    with write_transaction(session):
        record(
            session=session,
            user_id=user_id,
            action=action,
            resource_type=resource_type,
            resource_id=resource_id,
            details=details,
        )


def record(
    *,
    session: Session,
    user_id: int | None,
    action: str,
    resource_type: str,
    resource_id: int | None = None,
    details: dict[str, Any] | None = None,
) -> AuditEntry:
    entry = AuditEntry(
        user_id=user_id, action=action, resource_type=resource_type, resource_id=resource_id, details=details or {}
    )
    session.add(entry)
    return entry


def list_entries(
    *,
    session: Session,
    resource_type: str | None = None,
    resource_id: int | None = None,
    user_id: int | None = None,
    limit: int = 100,
    offset: int = 0,
) -> list[AuditEntry]:
    journal = journal_for(session)
    if journal is not None:
        if session.in_transaction():
            session.commit()  # end this read first: the drain commits on its own, and must not nest in it
        journal.drain()  # the log shows every read already answered
    # By time: journaled reads reach the table a moment after the changes around them.
    query = select(AuditEntry).order_by(AuditEntry.utc.desc(), AuditEntry.id.desc()).limit(limit).offset(offset)
    if resource_type is not None:
        query = query.where(AuditEntry.resource_type == resource_type)
    if resource_id is not None:
        query = query.where(AuditEntry.resource_id == resource_id)
    if user_id is not None:
        query = query.where(AuditEntry.user_id == user_id)
    return list(session.scalars(query))
