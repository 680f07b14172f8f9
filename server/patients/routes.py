"""`/patients`: list, create, read, update, delete, and each record's care team. Every route with a
`patient_id` is checked by `server.auth.access.object_access` (the router's dependency)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Response, status

from server.api_types import NO_NUL_PATTERN, IdPath, Limit, Offset
from server.auth.access import ObjectAccess
from server.auth.dependencies import CurrentUser, current_user
from server.concurrency import IfMatch, expected_version, with_etag
from server.db import SessionDep
from server.patients import service
from server.patients.schemas import CareTeamAdd, CareTeamMemberOut, PatientCreate, PatientOut, PatientUpdate

router = APIRouter(prefix="/patients", tags=["patients"], dependencies=[Depends(current_user), ObjectAccess])
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
        actor=user,
        search=search,
        diagnosis=diagnosis,
        include_archived=include_archived,
        limit=limit,
        offset=offset,
    )
    return [PatientOut.model_validate(p) for p in patients]


@router.post("", response_model=PatientOut, status_code=status.HTTP_201_CREATED)
def create_patient(data: PatientCreate, session: SessionDep, user: CurrentUser, response: Response) -> PatientOut:
    """Creates the record; its creator joins its care team."""
    patient = PatientOut.model_validate(service.create_patient(session=session, data=data, actor_id=user.id))
    with_etag(response, patient.version)
    return patient


@router.get("/{patient_id}", response_model=PatientOut)
def read_patient(patient_id: IdPath, session: SessionDep, user: CurrentUser, response: Response) -> PatientOut:
    """The record, with its version in `ETag` (send it back as `If-Match` to change it)."""
    patient = PatientOut.model_validate(service.read_patient(session=session, patient_id=patient_id, actor_id=user.id))
    with_etag(response, patient.version)
    return patient


@router.patch(
    "/{patient_id}",
    response_model=PatientOut,
    responses={
        412: {"description": "Changed by someone else since the version sent: names the current one"},
        428: {"description": "No If-Match (or expected_version): the version the change is based on is needed"},
    },
)
def update_patient(
    patient_id: IdPath,
    data: PatientUpdate,
    session: SessionDep,
    user: CurrentUser,
    response: Response,
    if_match: IfMatch = None,
) -> PatientOut:
    """Changes the fields sent, only if the record is still at the version sent (`If-Match` or
    `expected_version`); otherwise 412 naming who changed it and when."""
    based_on = expected_version(if_match, data.expected_version, resource="patient", resource_id=patient_id)
    patient = service.update_patient(
        session=session, patient_id=patient_id, data=data, actor_id=user.id, expected_version=based_on
    )
    answer = PatientOut.model_validate(patient)
    with_etag(response, answer.version)
    return answer


@router.delete("/{patient_id}", status_code=status.HTTP_204_NO_CONTENT)
def delete_patient(patient_id: IdPath, session: SessionDep, user: CurrentUser) -> Response:
    service.delete_patient(session=session, patient_id=patient_id, actor_id=user.id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


def _member_out(member: Any, user: Any) -> CareTeamMemberOut:
    return CareTeamMemberOut(
        user_id=user.id, username=user.username, full_name=user.full_name, role=user.role,
        added_by_id=member.added_by_id, added_at=member.added_at,
    )  # fmt: skip


@router.get("/{patient_id}/care-team", response_model=list[CareTeamMemberOut])
def care_team(patient_id: IdPath, session: SessionDep) -> list[CareTeamMemberOut]:
    """Who may see and change this record besides the admins."""
    return [_member_out(m, u) for m, u in service.care_team(session=session, patient_id=patient_id)]


@router.post("/{patient_id}/care-team", response_model=list[CareTeamMemberOut], status_code=status.HTTP_201_CREATED)
def add_care_team_member(
    patient_id: IdPath, data: CareTeamAdd, session: SessionDep, user: CurrentUser
) -> list[CareTeamMemberOut]:
    """A member (or an admin) adds a colleague, e.g. for cover or a handover; audited."""
    service.add_to_care_team(session=session, patient_id=patient_id, user_id=data.user_id, actor_id=user.id)
    return [_member_out(m, u) for m, u in service.care_team(session=session, patient_id=patient_id)]


@router.delete("/{patient_id}/care-team/{user_id}", status_code=status.HTTP_204_NO_CONTENT)
def remove_care_team_member(patient_id: IdPath, user_id: IdPath, session: SessionDep, user: CurrentUser) -> Response:
    """A member (or an admin) removes a clinician from the care team; audited."""
    service.remove_from_care_team(session=session, patient_id=patient_id, user_id=user_id, actor_id=user.id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
