"""Reading a run's durable session log back for the exporters (issue 6 §5, issue 20 Build 7): the telemetry
columns, the events with tick and UTC time and their detector, and the metadata sidecar built by
`server.exports.session_metadata` (patient pseudonymised unless an admin asks otherwise, prescription
version, washout parameters, geometry, software version)."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from typing import Any

import numpy as np
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from core.robot import TwinRobot
from server.errors import ConflictError, InvalidFieldError
from server.patients.models import Patient
from server.prescriptions.models import PrescriptionVersion
from server.robotd.models import SessionEvent, SessionRun, TelemetryChunk
from server.robotd.records import decode_chunk
from server.robotd.runs import get_run
from server.scheduling.models import ScheduledSession
from server.settings import Settings

MAX_RUNS_PER_BUNDLE = 200


def telemetry_columns(*, session: Session, run_id: int) -> dict[str, np.ndarray]:
    chunks = session.scalars(
        select(TelemetryChunk.data).where(TelemetryChunk.run_id == run_id).order_by(TelemetryChunk.sequence)
    ).all()
    if not chunks:
        raise ConflictError(f"session run {run_id} has no recorded telemetry to export")
    records = np.concatenate([decode_chunk(data) for data in chunks])
    return {name: np.ascontiguousarray(records[name]) for name in records.dtype.names or ()}


def sample_rate_hz(events: list[dict[str, Any]]) -> float:
    """The nominal control rate the run was recorded at (what C3D's ANALOG:RATE must say), from the worker's
    `prescription_loaded` event; runs recorded before it carried the rate get the configured default. The
    measured tick intervals are no substitute: under load they said 1075.28 Hz for a 1 kHz run."""
    for event in events:
        rate = event["details"].get("control_rate_hz") if event["kind"] == "prescription_loaded" else None
        if isinstance(rate, int | float) and not isinstance(rate, bool) and rate > 0:
            return float(rate)
    return float(Settings.model_fields["control_rate_hz"].default)


def event_record(event: SessionEvent) -> dict[str, Any]:
    """A stored event as the exporters take it (its tick may still be unknown: see
    `server.exports.stream.clocked_events`)."""
    return {
        "kind": event.kind,
        "tick": event.tick,
        "tick_time_s": event.tick_time_s,
        "utc": event.utc.isoformat(),
        "detector": event.detector,
        "details": dict(event.details),
    }


def patient_record(patient: Patient, *, include_free_text: bool = False) -> dict[str, Any]:
    """The patient fields an export may carry; the free-text notes only when the export asks for free text
    (the pseudonymiser drops the diagnosis too unless asked)."""
    record = {
        "identifier": patient.identifier,
        "name": patient.name,
        "date_of_birth": patient.date_of_birth.isoformat(),
        "sex": patient.sex,
        "height_m": patient.height_m,
        "body_mass_kg": patient.body_mass_kg,
        "diagnosis": patient.diagnosis,
        "affected_side": patient.affected_side,
    }
    if include_free_text:
        record["notes"] = patient.notes
    return record


def run_header(
    *, session: Session, run_id: int, twin: TwinRobot, salt: bytes, identify: bool, include_free_text: bool = False
) -> dict[str, Any]:
    """What an export needs of a run besides its telemetry: the metadata sidecar (`server.exports.
    session_metadata`) and the stored events, their ticks not yet placed (`clocked_events` does that)."""
    from server.exports import session_metadata

    run = get_run(session=session, run_id=run_id)
    booking = session.get(ScheduledSession, run.scheduled_session_id)
    version = session.get(PrescriptionVersion, run.prescription_version_id)
    assert booking is not None and version is not None  # foreign keys guarantee both
    patient = session.get(Patient, booking.patient_id)
    assert patient is not None
    stored = session.scalars(select(SessionEvent).where(SessionEvent.run_id == run.id).order_by(SessionEvent.id))
    events = [event_record(event) for event in stored]
    metadata = session_metadata(
        session_id=f"run-{run.id}",
        started_utc=run.started_at,
        sample_rate_hz=sample_rate_hz(events),
        patient=patient_record(patient, include_free_text=include_free_text),
        prescription=version.content,
        prescription_version=version.version,
        twin=twin,
        salt=salt,
        identified=identify,
        include_free_text=include_free_text,
    )
    metadata["run"] = {
        "id": run.id,
        "robot": run.robot,
        "outcome": run.outcome,
        "ended_utc": run.ended_at.isoformat() if run.ended_at else None,
        "prescription_id": version.prescription_id,
    }
    return {"metadata": metadata, "events": events}


def telemetry_blobs(*, session: Session, run_id: int) -> Iterator[bytes]:
    """The run's stored telemetry chunks (`.npy` blobs) in order, fetched a few at a time."""
    query = select(TelemetryChunk.data).where(TelemetryChunk.run_id == run_id).order_by(TelemetryChunk.sequence)
    found = False
    for data in session.execute(query.execution_options(yield_per=8)).scalars():
        found = True
        yield data
    if not found:
        raise ConflictError(f"session run {run_id} has no recorded telemetry to export")


def study_run_ids(*, session: Session, start: dt.date, end: dt.date, diagnosis: str | None) -> list[tuple[int, int]]:
    """(run id, patient id) of the recorded runs started on days start..end (UTC), optionally by diagnosis."""
    if end < start:
        raise InvalidFieldError("to_date", str(end), f"must not be before from_date {start}")
    query = (
        select(SessionRun.id, ScheduledSession.patient_id)
        .join(ScheduledSession, ScheduledSession.id == SessionRun.scheduled_session_id)
        .join(Patient, Patient.id == ScheduledSession.patient_id)
        .where(
            SessionRun.started_at >= dt.datetime.combine(start, dt.time(), dt.UTC),
            SessionRun.started_at < dt.datetime.combine(end + dt.timedelta(days=1), dt.time(), dt.UTC),
            SessionRun.sample_count > 0,
        )
        .order_by(SessionRun.id)
    )
    if diagnosis:
        query = query.where(func.lower(Patient.diagnosis) == diagnosis.lower())
    rows = [(run_id, patient_id) for run_id, patient_id in session.execute(query).tuples()]
    if len(rows) > MAX_RUNS_PER_BUNDLE:
        raise InvalidFieldError(
            "to_date", str(end), f"{len(rows)} runs match; at most {MAX_RUNS_PER_BUNDLE} per bundle"
        )
    return rows
