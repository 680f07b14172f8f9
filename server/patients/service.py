"""Patient service functions. Each change writes an audit entry in its transaction; each read is audited
through the audit journal (durable, off the request's database path: `server.audit.journal`)."""

from __future__ import annotations

import datetime as dt

from sqlalchemy import exists, func, select
from sqlalchemy.orm import Session

from server.audit import service as audit
from server.db import utc_now, writes
from server.errors import ConflictError, InvalidFieldError, NotFoundError, StaleVersionError
from server.patients.models import CareTeamMember, Patient
from server.patients.schemas import PatientCreate, PatientUpdate
from server.patients.search import fold
from server.users.models import User


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
    patient = Patient(**data.model_dump(), updated_by_id=actor_id)
    session.add(patient)
    session.flush()
    audit.record(session=session, user_id=actor_id, action="create", resource_type="patient", resource_id=patient.id)
    # The creator joins the care team; the "create" entry above records that already.
    session.add(CareTeamMember(patient_id=patient.id, user_id=actor_id, added_by_id=actor_id))
    return patient


def read_patient(*, session: Session, patient_id: int, actor_id: int) -> Patient:
    patient = find_patient(session=session, patient_id=patient_id)
    audit.record_read(session=session, user_id=actor_id, action="read", resource_type="patient", resource_id=patient.id)
    return patient


def list_patients(
    *,
    session: Session,
    actor: User,
    search: str | None = None,
    diagnosis: str | None = None,
    include_archived: bool = False,
    limit: int = 100,
    offset: int = 0,
) -> list[Patient]:
    from server.auth.access import restrict_to_care

    query = restrict_to_care(select(Patient), Patient.id, actor).order_by(Patient.name, Patient.id)
    query = query.limit(limit).offset(offset)
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
        user_id=actor.id,
        action="list",
        resource_type="patient",
        details={"patient_ids": [p.id for p in patients]},
    )
    return patients


def _refuse_stale(session: Session, patient: Patient, expected_version: int) -> None:
    if patient.version == expected_version:
        return
    changed_by = session.get(User, patient.updated_by_id) if patient.updated_by_id is not None else None
    raise StaleVersionError(
        "patient",
        patient.id,
        expected=expected_version,
        current=patient.version,
        changed_by=(changed_by.full_name or changed_by.username) if changed_by is not None else None,
        changed_at=patient.updated_at,
    )


@writes
def update_patient(
    *, session: Session, patient_id: int, data: PatientUpdate, actor_id: int, expected_version: int
) -> Patient:
    """Refused (412) unless the record is still at `expected_version`: two changes based on one version
    never both land. The UPDATE itself also names the version (the mapper's version column)."""
    patient = find_patient(session=session, patient_id=patient_id)
    _refuse_stale(session, patient, expected_version)
    changes = data.model_dump(exclude_unset=True, exclude_none=True, exclude={"expected_version"})
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
    if session.is_modified(patient):
        patient.updated_by_id = actor_id
        patient.updated_at = utc_now()  # also when only the archive flag changed: the version moves with it
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


# --- care team (docs/service.md, "Who may see and change what") ----------------------------------------


def care_team(*, session: Session, patient_id: int) -> list[tuple[CareTeamMember, User]]:
    find_patient(session=session, patient_id=patient_id)
    return [
        (member, user)
        for member, user in session.execute(
            select(CareTeamMember, User)
            .join(User, User.id == CareTeamMember.user_id)
            .where(CareTeamMember.patient_id == patient_id)
            .order_by(User.username)
        ).tuples()
    ]


def join_care_team(*, session: Session, patient_id: int, user_id: int, actor_id: int, reason: str) -> bool:
    """Adds `user_id` to the patient's care team inside the caller's transaction (audited); False if a member."""
    if session.get(CareTeamMember, (patient_id, user_id)) is not None:
        return False
    session.add(CareTeamMember(patient_id=patient_id, user_id=user_id, added_by_id=actor_id))
    session.flush()
    audit.record(
        session=session, user_id=actor_id, action="care_team_add", resource_type="patient", resource_id=patient_id,
        details={"user_id": user_id, "reason": reason},
    )  # fmt: skip
    return True


@writes
def add_to_care_team(*, session: Session, patient_id: int, user_id: int, actor_id: int) -> CareTeamMember:
    find_patient(session=session, patient_id=patient_id)
    user = session.get(User, user_id)
    if user is None:
        raise NotFoundError("user", user_id)
    if not user.is_active:
        raise InvalidFieldError("user_id", user_id, "must be an active account")
    join_care_team(session=session, patient_id=patient_id, user_id=user_id, actor_id=actor_id, reason="added")
    member = session.get(CareTeamMember, (patient_id, user_id))
    assert member is not None
    return member


@writes
def remove_from_care_team(*, session: Session, patient_id: int, user_id: int, actor_id: int) -> None:
    member = session.get(CareTeamMember, (patient_id, user_id))
    if member is None:
        raise NotFoundError(f"care team member of patient {patient_id}: user", user_id)
    session.delete(member)
    audit.record(
        session=session, user_id=actor_id, action="care_team_remove", resource_type="patient", resource_id=patient_id,
        details={"user_id": user_id},
    )  # fmt: skip
