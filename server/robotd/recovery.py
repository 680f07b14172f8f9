"""Closing runs a crash left open: on any start (the daemon's, or a web process's while no daemon runs),
every open run of the robot gets what its journal holds and the database lacks (telemetry after the
last stored chunk, events and the daemon's pause/resume decisions not yet stored) and a `daemon_lost`
event saying what is known of the stop, then ends: as the daemon had decided when its journal holds the
end (a stop during a database outage, say), else as `interrupted`, at the true time: the last moment
anything of it was recorded."""

from __future__ import annotations

import datetime as dt
import logging
from pathlib import Path

import numpy as np
from sqlalchemy import func, select

from server.db import Database, write_transaction
from server.robotd import runs
from server.robotd.journal import read_decisions, read_journal, remove_journal
from server.robotd.models import ACTIVE_STATES, RunOutcome, SessionEvent, SessionRun, TelemetryChunk
from server.robotd.records import decode_chunk, encode_chunk, event_row, event_utc

log = logging.getLogger("ssp_rehab.robotd")


def _event_key(kind: str, utc: dt.datetime) -> tuple[str, int]:
    moment = utc if utc.tzinfo else utc.replace(tzinfo=dt.UTC)
    return kind[:32], round(moment.timestamp() * 1000)


def recover_open_runs(
    *, database: Database, robot: str, journal_dir: Path, lost_daemon_pid: int | None = None
) -> list[int]:
    """Close every open run of `robot` as interrupted; returns their ids. Only call it while no daemon
    runs for `robot` (the caller holds its lock, or found it free). `lost_daemon_pid`: the pid file the
    dead daemon left, where known."""
    with database.session() as session:
        open_runs = list(
            session.scalars(select(SessionRun.id).where(SessionRun.robot == robot, SessionRun.state.in_(ACTIVE_STATES)))
        )
    for run_id in open_runs:
        _recover(database, run_id, journal_dir, lost_daemon_pid)
    return open_runs


def _recover(database: Database, run_id: int, journal_dir: Path, lost_daemon_pid: int | None) -> None:
    records, events = read_journal(journal_dir, run_id)
    decisions = read_decisions(journal_dir, run_id)
    end = next((d for d in decisions if d.get("decision") == "end"), None)
    # The daemon's pause and resume, as the events `record_command` would have written.
    for decision in decisions:
        if decision.get("decision") in ("pause", "resume"):
            credential = decision.get("credential")
            events.append(
                {
                    **{key: decision.get(key) for key in ("tick", "tick_time_s", "utc", "user_id")},
                    "kind": decision["decision"],
                    "detector": "console",
                    "details": {"credential": credential} if credential else {},
                }
            )
    with database.session() as session, write_transaction(session):
        run = session.get(SessionRun, run_id)
        assert run is not None
        last_moment = run.started_at if run.started_at.tzinfo else run.started_at.replace(tzinfo=dt.UTC)
        stored_chunks = session.scalars(select(TelemetryChunk.data).where(TelemetryChunk.run_id == run_id)).all()
        decoded = [decode_chunk(blob) for blob in stored_chunks]
        last_tick = max((int(chunk["tick"].max()) for chunk in decoded if len(chunk)), default=-1)
        for chunk in decoded:
            if len(chunk):
                last_moment = max(last_moment, dt.datetime.fromtimestamp(float(chunk["utc_s"].max()), dt.UTC))
        sequence = session.scalar(
            select(func.coalesce(func.max(TelemetryChunk.sequence), -1)).where(TelemetryChunk.run_id == run_id)
        )
        recovered_samples, recovered_events = 0, 0
        if records is not None and len(records):
            missing = records[records["tick"] > last_tick]
            if len(missing):
                session.add(
                    TelemetryChunk(
                        run_id=run_id,
                        sequence=int(sequence if sequence is not None else -1) + 1,
                        first_tick=int(missing["tick"][0]),
                        sample_count=len(missing),
                        data=encode_chunk(np.ascontiguousarray(missing)),
                    )
                )
                run.sample_count += len(missing)
                recovered_samples = len(missing)
            last_moment = max(last_moment, dt.datetime.fromtimestamp(float(records["utc_s"][-1]), dt.UTC))
        stored_events = list(
            session.execute(select(SessionEvent.kind, SessionEvent.utc).where(SessionEvent.run_id == run_id))
        )
        stored = {_event_key(kind, utc) for kind, utc in stored_events}
        for _kind, utc in stored_events:
            last_moment = max(last_moment, utc if utc.tzinfo else utc.replace(tzinfo=dt.UTC))
        for event in events:
            utc = event_utc(event.get("utc"))
            last_moment = max(last_moment, utc)
            if _event_key(str(event.get("kind")), utc) in stored:
                continue
            recovered_events += 1
            session.add(event_row(run_id, event))
        if _event_key("daemon_lost", last_moment) not in stored:
            session.add(
                SessionEvent(
                    run_id=run_id,
                    kind="daemon_lost",
                    utc=last_moment,
                    detector="robot daemon",
                    details={
                        "pid": lost_daemon_pid,
                        "what": "the robot daemon ended during the run (killed or crashed); its worker stops the "
                        "motion when it loses the daemon, and the drives stop on their own heartbeat loss",
                        "last_record_utc": last_moment.isoformat(),
                        "samples_recovered_from_journal": recovered_samples,
                        "events_recovered_from_journal": recovered_events,
                    },
                )
            )
    with database.session() as session:
        if end is not None:  # decided and journalled by the daemon before the database heard of it
            runs.end_run(
                session=session,
                run_id=run_id,
                outcome=RunOutcome(end["outcome"]),
                at=event_utc(end.get("utc")),
                reason=str(end.get("reason")),
                clock=(end.get("tick"), end.get("tick_time_s")),
                stopped_by_id=end.get("user_id"),
                credential=end.get("credential"),
            )
        else:
            runs.end_run(
                session=session,
                run_id=run_id,
                outcome=RunOutcome.INTERRUPTED,
                at=last_moment,
                reason="left open by a crash; closed on the next start at the time of its last record",
            )
    remove_journal(journal_dir, run_id)
    outcome = end["outcome"] if end is not None else "interrupted"
    log.warning("run %d was left open by a crash: closed as %s at %s", run_id, outcome, last_moment.isoformat())
