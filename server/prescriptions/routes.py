"""`/prescriptions`: create, list, read, revise (new version), read a given version."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Path, Query, Request, Response, status

from server.api_types import MAX_ID, IdPath, Limit, Offset
from server.auth.access import ObjectAccess, require_patient
from server.auth.dependencies import CurrentUser, current_user
from server.concurrency import IfMatch, expected_version, with_etag
from server.db import SessionDep
from server.prescriptions import service
from server.prescriptions.models import Prescription
from server.prescriptions.schemas import (
    PrescriptionCreate,
    PrescriptionOut,
    PrescriptionRevise,
    PrescriptionVersionOut,
)

router = APIRouter(prefix="/prescriptions", tags=["prescriptions"], dependencies=[Depends(current_user), ObjectAccess])
VersionPath = Annotated[int, Path(ge=1, le=MAX_ID)]


def _out(prescription: Prescription) -> PrescriptionOut:
    current = PrescriptionVersionOut.model_validate(service.latest(prescription))
    return PrescriptionOut(
        id=prescription.id,
        patient_id=prescription.patient_id,
        name=prescription.name,
        latest_version=prescription.latest_version,
        created_at=prescription.created_at,
        current=current,
    )


def _robot(request: Request) -> dict[str, Any]:
    """The robot a prescription must fit (its limits may only be tightened) and its control rate."""
    return {"twin": request.app.state.twin, "control_rate_hz": request.app.state.settings.control_rate_hz}


@router.get("", response_model=list[PrescriptionOut])
def list_prescriptions(
    session: SessionDep,
    user: CurrentUser,
    patient_id: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> list[PrescriptionOut]:
    prescriptions = service.list_prescriptions(
        session=session, actor=user, patient_id=patient_id, limit=limit, offset=offset
    )
    return [_out(p) for p in prescriptions]


@router.post("", response_model=PrescriptionOut, status_code=status.HTTP_201_CREATED)
def create_prescription(
    data: PrescriptionCreate, request: Request, session: SessionDep, user: CurrentUser, response: Response
) -> PrescriptionOut:
    require_patient(session, user, data.patient_id)
    prescription = service.create_prescription(session=session, data=data, actor_id=user.id, **_robot(request))
    with_etag(response, prescription.latest_version)
    return _out(prescription)


@router.get("/{prescription_id}", response_model=PrescriptionOut)
def get_prescription(prescription_id: IdPath, session: SessionDep, response: Response) -> PrescriptionOut:
    """The prescription and its current version, whose number is the `ETag` (send it as `If-Match` to revise)."""
    prescription = service.get_prescription(session=session, prescription_id=prescription_id)
    with_etag(response, prescription.latest_version)
    return _out(prescription)


@router.put(
    "/{prescription_id}",
    response_model=PrescriptionOut,
    responses={
        412: {"description": "Revised by someone else since the version sent: names the current one"},
        428: {"description": "No If-Match (or expected_version): the version the revision is based on is needed"},
    },
)
def revise_prescription(
    prescription_id: IdPath,
    data: PrescriptionRevise,
    request: Request,
    session: SessionDep,
    user: CurrentUser,
    response: Response,
    if_match: IfMatch = None,
) -> PrescriptionOut:
    """Editing creates a new version; sessions keep referring to the version they were scheduled with. Only
    if the current version is still the one sent (`If-Match` or `expected_version`), else 412."""
    based_on = expected_version(if_match, data.expected_version, resource="prescription", resource_id=prescription_id)
    prescription = service.revise_prescription(
        session=session,
        prescription_id=prescription_id,
        data=data,
        actor_id=user.id,
        expected_version=based_on,
        **_robot(request),
    )
    with_etag(response, prescription.latest_version)
    return _out(prescription)


@router.get("/{prescription_id}/versions", response_model=list[PrescriptionVersionOut])
def list_versions(prescription_id: IdPath, session: SessionDep) -> list[PrescriptionVersionOut]:
    prescription = service.get_prescription(session=session, prescription_id=prescription_id)
    return [PrescriptionVersionOut.model_validate(v) for v in prescription.versions]


@router.get("/{prescription_id}/versions/{version}", response_model=PrescriptionVersionOut)
def get_version(prescription_id: IdPath, version: VersionPath, session: SessionDep) -> PrescriptionVersionOut:
    found = service.get_version(session=session, prescription_id=prescription_id, version=version)
    return PrescriptionVersionOut.model_validate(found)
