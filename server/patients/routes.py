"""`/patients`: list, create, read, update, delete."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Response, status

from server.api_types import NO_NUL_PATTERN, IdPath, Limit, Offset
from server.auth.dependencies import CurrentUser, current_user
from server.db import SessionDep
from server.patients import service
from server.patients.schemas import PatientCreate, PatientOut, PatientUpdate

router = APIRouter(prefix="/patients", tags=["patients"], dependencies=[Depends(current_user)])
SearchText = Annotated[str | None, Query(max_length=200, pattern=NO_NUL_PATTERN)]


@router.get("", response_model=list[PatientOut])
def list_patients(
    session: SessionDep,
    user: CurrentUser,
    search: Annotated[
        str | None,
        Query(
            max_length=200,
            pattern=NO_NUL_PATTERN,
            description="Part of the name or identifier; accents and case are ignored.",
        ),
    ] = None,
    diagnosis: SearchText = None,
    include_archived: Annotated[bool, Query(description="Also list archived records.")] = False,
    limit: Limit = 100,
    offset: Offset = 0,
) -> list[PatientOut]:
    patients = service.list_patients(
        session=session,
        actor_id=user.id,
        search=search,
        diagnosis=diagnosis,
        include_archived=include_archived,
        limit=limit,
        offset=offset,
    )
    return [PatientOut.model_validate(p) for p in patients]


@router.post("", response_model=PatientOut, status_code=status.HTTP_201_CREATED)
def create_patient(data: PatientCreate, session: SessionDep, user: CurrentUser) -> PatientOut:
    return PatientOut.model_validate(service.create_patient(session=session, data=data, actor_id=user.id))


@router.get("/{patient_id}", response_model=PatientOut)
def read_patient(patient_id: IdPath, session: SessionDep, user: CurrentUser) -> PatientOut:
    return PatientOut.model_validate(service.read_patient(session=session, patient_id=patient_id, actor_id=user.id))


@router.patch("/{patient_id}", response_model=PatientOut)
def update_patient(patient_id: IdPath, data: PatientUpdate, session: SessionDep, user: CurrentUser) -> PatientOut:
    patient = service.update_patient(session=session, patient_id=patient_id, data=data, actor_id=user.id)
    return PatientOut.model_validate(patient)


@router.delete("/{patient_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_patient(patient_id: IdPath, session: SessionDep, user: CurrentUser) -> Response:
    service.delete_patient(session=session, patient_id=patient_id, actor_id=user.id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
