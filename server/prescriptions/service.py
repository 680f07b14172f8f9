"""Prescription service functions. Versions are immutable: a revision adds version n+1."""

from __future__ import annotations

from typing import Any

from sqlalchemy import select
from sqlalchemy.orm import Session

from core.plan.build import check_for_robot
from core.plan.prescription import PrescriptionBody, PrescriptionError
from core.robot import TwinRobot
from server.audit import service as audit
from server.db import writes
from server.errors import InvalidFieldError, NotFoundError, StaleVersionError
from server.patients.service import find_patient
from server.prescriptions.models import Prescription, PrescriptionVersion
from server.prescriptions.schemas import PrescriptionCreate, PrescriptionRevise
from server.users.models import User

KEPT_ON_REVISION = ("cueing", "seed")


def _content(data: PrescriptionBody, twin: TwinRobot, control_rate_hz: int) -> dict[str, Any]:
    """What is stored: the model validated the request; this robot may only tighten its limits (and the
    shaping must hold at its control rate). Refused before any write."""
    try:
        check_for_robot(data, twin, control_rate_hz=control_rate_hz)
    except PrescriptionError as error:
        raise InvalidFieldError(error.field, error.value, error.limit) from None
    return data.content()


def get_prescription(*, session: Session, prescription_id: int) -> Prescription:
    prescription = session.get(Prescription, prescription_id)
    if prescription is None:
        raise NotFoundError("prescription", prescription_id)
    return prescription


def get_version(*, session: Session, prescription_id: int, version: int) -> PrescriptionVersion:
    found = session.scalar(
        select(PrescriptionVersion).where(
            PrescriptionVersion.prescription_id == prescription_id, PrescriptionVersion.version == version
        )
    )
    if found is None:
        raise NotFoundError(f"prescription {prescription_id} version", version)
    return found


def latest(prescription: Prescription) -> PrescriptionVersion:
    return prescription.versions[-1]


@writes
def create_prescription(
    *, session: Session, data: PrescriptionCreate, twin: TwinRobot, control_rate_hz: int, actor_id: int
) -> Prescription:
    find_patient(session=session, patient_id=data.patient_id)
    content = _content(data, twin, control_rate_hz)
    prescription = Prescription(patient_id=data.patient_id, name=data.name, latest_version=1, created_by_id=actor_id)
    prescription.versions.append(
        PrescriptionVersion(version=1, content=content, note=data.note, created_by_id=actor_id)
    )
    session.add(prescription)
    session.flush()
    audit.record(
        session=session,
        user_id=actor_id,
        action="create",
        resource_type="prescription",
        resource_id=prescription.id,
        details={"patient_id": data.patient_id, "version": 1},
    )
    return prescription


@writes
def revise_prescription(
    *,
    session: Session,
    prescription_id: int,
    data: PrescriptionRevise,
    twin: TwinRobot,
    control_rate_hz: int,
    actor_id: int,
    expected_version: int,
) -> Prescription:
    """Adds version n+1, only if n is still `expected_version` (else 412 naming who revised it and when)."""
    prescription = get_prescription(session=session, prescription_id=prescription_id)
    if prescription.latest_version != expected_version:
        current_version = latest(prescription)
        author = session.get(User, current_version.created_by_id) if current_version.created_by_id else None
        raise StaleVersionError(
            "prescription",
            prescription.id,
            expected=expected_version,
            current=prescription.latest_version,
            changed_by=(author.full_name or author.username) if author is not None else None,
            changed_at=current_version.created_at,
        )
    # A revision that sends only new segments keeps the current cueing algorithm and seed.
    current = latest(prescription).content
    kept = {name: current[name] for name in KEPT_ON_REVISION if name not in data.model_fields_set and name in current}
    content = _content(data.model_copy(update=kept), twin, control_rate_hz)
    prescription.latest_version += 1
    if data.name is not None:
        prescription.name = data.name
    prescription.versions.append(
        PrescriptionVersion(
            version=prescription.latest_version, content=content, note=data.note, created_by_id=actor_id
        )
    )
    audit.record(
        session=session,
        user_id=actor_id,
        action="update",
        resource_type="prescription",
        resource_id=prescription.id,
        details={"patient_id": prescription.patient_id, "version": prescription.latest_version},
    )
    return prescription


def list_prescriptions(
    *, session: Session, actor: User, patient_id: int | None = None, limit: int = 100, offset: int = 0
) -> list[Prescription]:
    from server.auth.access import restrict_to_care

    query = restrict_to_care(select(Prescription), Prescription.patient_id, actor)
    query = query.order_by(Prescription.id).limit(limit).offset(offset)
    if patient_id is not None:
        query = query.where(Prescription.patient_id == patient_id)
    return list(session.scalars(query))
