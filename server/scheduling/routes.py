"""`/sessions` (scheduled sessions), `/series/{id}/cancel`, `/therapists/{id}/calendar.ics`."""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Depends, Query, Response, status
from pydantic import AwareDatetime

from server.api_types import MAX_ID, IdPath, Limit, Offset
from server.auth.dependencies import CurrentUser, current_user
from server.db import SessionDep
from server.scheduling import service
from server.scheduling.schemas import RobotName, ScheduleCreate, ScheduledSessionOut, ScheduleUpdate

router = APIRouter(tags=["scheduling"], dependencies=[Depends(current_user)])
OptionalId = Annotated[int | None, Query(ge=1, le=MAX_ID)]


@router.get("/sessions", response_model=list[ScheduledSessionOut])
def list_sessions(
    session: SessionDep,
    start: Annotated[AwareDatetime | None, Query(alias="from", description="Bookings ending after this.")] = None,
    end: Annotated[AwareDatetime | None, Query(alias="to", description="Bookings starting before this.")] = None,
    robot: Annotated[RobotName | None, Query()] = None,
    patient_id: OptionalId = None,
    therapist_id: OptionalId = None,
    status_filter: Annotated[Literal["scheduled", "cancelled", "completed"] | None, Query(alias="status")] = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> list[ScheduledSessionOut]:
    rows = service.list_bookings(
        session=session,
        start=start,
        end=end,
        robot=robot,
        patient_id=patient_id,
        therapist_id=therapist_id,
        status=status_filter,
        limit=limit,
        offset=offset,
    )
    return [service.to_out(*row) for row in rows]


@router.post(
    "/sessions",
    response_model=list[ScheduledSessionOut],
    status_code=status.HTTP_201_CREATED,
    responses={409: {"description": "The robot or the patient is already booked"}},
)
def create_sessions(data: ScheduleCreate, session: SessionDep, user: CurrentUser) -> list[ScheduledSessionOut]:
    """Books one session, or every occurrence of a recurring series (all or none)."""
    bookings = service.create_booking(session=session, data=data, actor_id=user.id)
    return [service.booking_out(session=session, booking=b) for b in bookings]


@router.get("/sessions/{session_id}", response_model=ScheduledSessionOut)
def get_session(session_id: IdPath, session: SessionDep) -> ScheduledSessionOut:
    return service.booking_out(session=session, booking=service.get_booking(session=session, session_id=session_id))


@router.patch(
    "/sessions/{session_id}", response_model=ScheduledSessionOut, responses={409: {"description": "Conflict"}}
)
def update_session(
    session_id: IdPath, data: ScheduleUpdate, session: SessionDep, user: CurrentUser
) -> ScheduledSessionOut:
    booking = service.update_booking(session=session, session_id=session_id, data=data, actor_id=user.id)
    return service.booking_out(session=session, booking=booking)


@router.post("/series/{series_id}/cancel", response_model=list[ScheduledSessionOut])
def cancel_series(series_id: IdPath, session: SessionDep, user: CurrentUser) -> list[ScheduledSessionOut]:
    bookings = service.cancel_series(session=session, series_id=series_id, actor_id=user.id)
    return [service.booking_out(session=session, booking=b) for b in bookings]


@router.get(
    "/therapists/{therapist_id}/calendar.ics",
    response_class=Response,
    responses={200: {"content": {"text/calendar": {}}, "description": "iCalendar feed"}},
)
def therapist_calendar(therapist_id: IdPath, session: SessionDep) -> Response:
    body = service.therapist_calendar(
        session=session, therapist_id=therapist_id, product_id="-//ssp-rehab//console//EN"
    )
    return Response(body, media_type="text/calendar; charset=utf-8")
