"""Patient service functions. Each change writes an audit entry in its transaction; each read is audited
through the audit journal (durable, off the request's database path: `server.audit.journal`)."""

from __future__ import annotations

import datetime as dt

from sqlalchemy import exists, func, select
from sqlalchemy.orm import Session

from server.audit import service as audit
from server.db import writes
from server.errors import ConflictError, NotFoundError
from server.patients.models import Patient
from server.patients.schemas import PatientCreate, PatientUpdate
from server.patients.search import fold


def _identifier_taken(session: Session, identifier: str, except_id: int | None = None) -> bool:
    query = select(Patient.id).where(Patient.identifier == identifier)
    if except_id is not None:
        query = query.where(Patient.id != except_id)
    return session.scalar(query) is not None


def find_patient(*, session: Session, patient_id: int) -> Patient:
    """The patient, without an audit entry: for internal use by other services."""
    patient = session.get(Patient, patient_id)
    if patient is None:
        raise NotFoundError("patient", patient_id)
    return patient


@writes
def create_patient(*, session: Session, data: PatientCreate, actor_id: int) -> Patient:
    if _identifier_taken(session, data.identifier):
        raise ConflictError("identifier is already used by another patient", field="identifier")
    patient = Patient(**data.model_dump())
    session.add(patient)
    session.flush()
    audit.record(session=session, user_id=actor_id, action="create", resource_type="patient", resource_id=patient.id)
    return patient


def read_patient(*, session: Session, patient_id: int, actor_id: int) -> Patient:
    patient = find_patient(session=session, patient_id=patient_id)
    audit.record_read(session=session, user_id=actor_id, action="read", resource_type="patient", resource_id=patient.id)
    return patient


def list_patients(
    *,
    session: Session,
    actor_id: int,
    search: str | None = None,
    diagnosis: str | None = None,
    include_archived: bool = False,
    limit: int = 100,
    offset: int = 0,
) -> list[Patient]:
    query = select(Patient).order_by(Patient.name, Patient.id).limit(limit).offset(offset)
    if search:
        # LIKE's own wildcards in the search text match literally.
        escaped = fold(search).replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")
        query = query.where(Patient.search_key.like(f"%{escaped}%", escape="\\"))
    if not include_archived:
        query = query.where(Patient.archived_at.is_(None))
    if diagnosis:
        query = query.where(func.lower(Patient.diagnosis) == diagnosis.lower())
    patients = list(session.scalars(query))
    # A listing shows names and record numbers, so it counts as reading each of those records.
    audit.record_read(
        session=session,
        user_id=actor_id,
        action="list",
        resource_type="patient",
        details={"patient_ids": [p.id for p in patients]},
    )
    return patients


@writes
def update_patient(*, session: Session, patient_id: int, data: PatientUpdate, actor_id: int) -> Patient:
    patient = find_patient(session=session, patient_id=patient_id)
    changes = data.model_dump(exclude_unset=True, exclude_none=True)
    if "identifier" in changes and _identifier_taken(session, changes["identifier"], except_id=patient.id):
        raise ConflictError("identifier is already used by another patient", field="identifier")
    archived = changes.pop("archived", None)
    for name, value in changes.items():
        setattr(patient, name, value)
    if archived is not None and archived != (patient.archived_at is not None):
        patient.archived_at = dt.datetime.now(dt.UTC) if archived else None
        audit.record(
            session=session, user_id=actor_id, action="archive" if archived else "restore", resource_type="patient",
            resource_id=patient.id,
        )  # fmt: skip
    if not changes:
        return patient
    audit.record(
        session=session,
        user_id=actor_id,
        action="update",
        resource_type="patient",
        resource_id=patient.id,
        details={"fields": sorted(changes)},
    )
    return patient


@writes
def delete_patient(*, session: Session, patient_id: int, actor_id: int) -> None:
    from server.prescriptions.models import Prescription
    from server.scheduling.models import ScheduledSession

    patient = find_patient(session=session, patient_id=patient_id)
    referenced = session.scalar(
        select(
            exists().where(Prescription.patient_id == patient.id)
            | exists().where(ScheduledSession.patient_id == patient.id)
        )
    )
    if referenced:
        raise ConflictError("patient has prescriptions or sessions: the record must be kept")
    session.delete(patient)
    audit.record(session=session, user_id=actor_id, action="delete", resource_type="patient", resource_id=patient_id)
