"""`/sessions` (scheduled sessions), `/schedule/week`, `/series/{id}/cancel`, the therapist's iCalendar
feed (`/therapists/{id}/calendar.ics` with a login, `/calendar/{token}.ics` for calendar apps)."""

from __future__ import annotations

import datetime as dt
import logging
from typing import Annotated, Literal
from zoneinfo import ZoneInfo

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request, Response, status
from pydantic import AwareDatetime, Field

from server.api_types import MAX_ID, IdPath, Limit, Offset, ResponseModel
from server.audit import service as audit
from server.auth.access import ObjectAccess, patients_in_care, require_object, require_patient
from server.auth.dependencies import CurrentUser, current_user
from server.db import SessionDep
from server.scheduling import service
from server.scheduling.schemas import (
    PlanStateOut,
    RobotName,
    ScheduleCreate,
    ScheduledSessionOut,
    ScheduleUpdate,
    WeekOut,
)

logger = logging.getLogger(__name__)
router = APIRouter(tags=["scheduling"], dependencies=[Depends(current_user), ObjectAccess])
# Calendar apps cannot log in: the secret in the path is the credential, one per therapist, revocable.
public_router = APIRouter(tags=["scheduling"])
OptionalId = Annotated[int | None, Query(ge=1, le=MAX_ID)]
PRODUCT_ID = "-//ssp-rehab//console//EN"
CALENDAR_MEDIA_TYPE = "text/calendar; charset=utf-8"


def clinic_zone(request: Request) -> ZoneInfo:
    zone: ZoneInfo = request.app.state.settings.clinic_zone()
    return zone


ClinicZone = Annotated[ZoneInfo, Depends(clinic_zone)]


@router.get("/sessions", response_model=list[ScheduledSessionOut])
def list_sessions(
    session: SessionDep,
    user: CurrentUser,
    zone: ClinicZone,
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
        actor=user,
        start=start,
        end=end,
        robot=robot,
        patient_id=patient_id,
        therapist_id=therapist_id,
        status=status_filter,
        limit=limit,
        offset=offset,
    )
    return [service.to_out(*row, zone) for row in rows]


@router.get("/schedule/week", response_model=WeekOut)
def schedule_week(
    session: SessionDep,
    user: CurrentUser,
    zone: ClinicZone,
    day: Annotated[
        dt.date | None, Query(description="Any day of the wanted clinic-local week; default: today.")
    ] = None,
    robot: Annotated[RobotName | None, Query()] = None,
) -> Response:
    """The clinic-local week (Monday 00:00 to Monday 00:00 in SSP_REHAB_TIMEZONE) with each booking's
    patient name and run summary: everything the week view shows, in one request."""
    answer = service.week(
        session=session,
        day=day or dt.datetime.now(zone).date(),
        zone=zone,
        robot=robot,
        shown=lambda ids: patients_in_care(session, user, ids),
    )
    # The week shows patient names, so it counts as reading those records.
    patient_ids = sorted({b.patient_id for b in answer.bookings if b.in_care})
    audit.record_read(
        session=session, user_id=user.id, action="list", resource_type="patient", details={"patient_ids": patient_ids}
    )
    # Serialised once by pydantic-core, not validated again on the way out (response_model only documents it).
    return Response(answer.model_dump_json(), media_type="application/json")


@router.post(
    "/sessions",
    response_model=list[ScheduledSessionOut],
    status_code=status.HTTP_201_CREATED,
    responses={409: {"description": "The robot or the patient is already booked"}},
)
def create_sessions(
    data: ScheduleCreate, session: SessionDep, user: CurrentUser, zone: ClinicZone, request: Request
) -> list[ScheduledSessionOut]:
    """Books one session, or every occurrence of a recurring series (all or none). A series keeps the
    first occurrence's clinic-local wall time; one that would fall in a DST gap or overlap is refused."""
    require_patient(session, user, data.patient_id)
    require_object(session, user, "prescription_id", data.prescription_id)
    bookings = service.create_booking(session=session, data=data, actor_id=user.id, zone=zone)
    session.commit()  # the robot daemon reads the bookings to plan them
    return [_with_plan(request, service.booking_out(session=session, booking=b, zone=zone)) for b in bookings]


@router.get("/sessions/{session_id}", response_model=ScheduledSessionOut)
def get_session(session_id: IdPath, session: SessionDep, zone: ClinicZone, request: Request) -> ScheduledSessionOut:
    """The booking, with its plan's state: opening the session page has its plan built if it is not yet."""
    booking = service.get_booking(session=session, session_id=session_id)
    return _with_plan(request, service.booking_out(session=session, booking=booking, zone=zone))


@router.patch(
    "/sessions/{session_id}", response_model=ScheduledSessionOut, responses={409: {"description": "Conflict"}}
)
def update_session(
    session_id: IdPath,
    data: ScheduleUpdate,
    session: SessionDep,
    user: CurrentUser,
    zone: ClinicZone,
    request: Request,
) -> ScheduledSessionOut:
    booking = service.update_booking(session=session, session_id=session_id, data=data, actor_id=user.id, zone=zone)
    session.commit()  # the robot daemon reads the moved booking to plan it
    return _with_plan(request, service.booking_out(session=session, booking=booking, zone=zone))


def _with_plan(request: Request, booking: ScheduledSessionOut) -> ScheduledSessionOut:
    """The booking with its plan's state from this console's robot daemon (which queues the plan if it is
    neither stored nor being built); without an answer, none."""
    robot = request.app.state.robot
    if robot is None or booking.robot != robot.robot or booking.status == "cancelled":
        return booking
    try:
        state = robot.plan_status(booking.id)
    except Exception as error:  # no daemon, or a slow one: the booking still answers
        logger.info("plan state of session %d unknown: %s", booking.id, error)
        return booking
    return booking.model_copy(update={"plan": PlanStateOut(**state)} if state else {})


@router.post("/series/{series_id}/cancel", response_model=list[ScheduledSessionOut])
def cancel_series(
    series_id: IdPath, session: SessionDep, user: CurrentUser, zone: ClinicZone
) -> list[ScheduledSessionOut]:
    bookings = service.cancel_series(session=session, series_id=series_id, actor_id=user.id)
    return [service.booking_out(session=session, booking=b, zone=zone) for b in bookings]


@router.get(
    "/therapists/{therapist_id}/calendar.ics",
    response_class=Response,
    responses={
        200: {"content": {"text/calendar": {}}, "description": "iCalendar feed"},
        403: {"description": "Another therapist's feed"},
    },
)
def therapist_calendar(therapist_id: IdPath, session: SessionDep, user: CurrentUser, zone: ClinicZone) -> Response:
    body = service.therapist_calendar(session=session, therapist_id=therapist_id, product_id=PRODUCT_ID, zone=zone)
    return Response(body, media_type=CALENDAR_MEDIA_TYPE)


class CalendarSubscriptionOut(ResponseModel):
    therapist_id: int
    url: str | None = Field(None, description="The secret link for calendar apps; shown only when issued.")
    issued_at: dt.datetime | None = None


@router.get("/therapists/{therapist_id}/calendar-subscription", response_model=CalendarSubscriptionOut)
def calendar_subscription(therapist_id: IdPath, session: SessionDep, user: CurrentUser) -> CalendarSubscriptionOut:
    """Whether a subscription link exists (the link itself is shown only once, when it is issued)."""
    issued = service.calendar_token_issued_at(session=session, therapist_id=therapist_id)
    return CalendarSubscriptionOut(therapist_id=therapist_id, url=None, issued_at=issued)


@router.post(
    "/therapists/{therapist_id}/calendar-subscription",
    response_model=CalendarSubscriptionOut,
    status_code=status.HTTP_201_CREATED,
)
def issue_calendar_subscription(
    therapist_id: IdPath, session: SessionDep, user: CurrentUser, request: Request
) -> CalendarSubscriptionOut:
    """A new secret subscription link for calendar apps (path under the API); any earlier link stops working."""
    token = service.issue_calendar_token(session=session, therapist_id=therapist_id, actor_id=user.id)
    issued = service.calendar_token_issued_at(session=session, therapist_id=therapist_id)
    url = str(request.url_for("subscribed_calendar", token=token))
    return CalendarSubscriptionOut(therapist_id=therapist_id, url=url, issued_at=issued)


@router.delete("/therapists/{therapist_id}/calendar-subscription", status_code=status.HTTP_204_NO_CONTENT)
def revoke_calendar_subscription(therapist_id: IdPath, session: SessionDep, user: CurrentUser) -> Response:
    service.revoke_calendar_token(session=session, therapist_id=therapist_id, actor_id=user.id)
    return Response(status_code=status.HTTP_204_NO_CONTENT)


@public_router.get(
    "/calendar/{token}.ics",
    name="subscribed_calendar",
    response_class=Response,
    responses={200: {"content": {"text/calendar": {}}, "description": "iCalendar feed"}, 404: {}},
)
def subscribed_calendar(
    token: Annotated[str, Path(min_length=20, max_length=100, pattern=r"^[A-Za-z0-9_-]+$")],
    session: SessionDep,
    zone: ClinicZone,
) -> Response:
    """The feed of the one therapist this secret link belongs to; unknown or revoked links get 404."""
    therapist_id = service.therapist_for_calendar_token(session=session, token=token)
    if therapist_id is None:
        raise HTTPException(status.HTTP_404_NOT_FOUND, detail="calendar link unknown or revoked: issue a new one")
    body = service.therapist_calendar(session=session, therapist_id=therapist_id, product_id=PRODUCT_ID, zone=zone)
    return Response(body, media_type=CALENDAR_MEDIA_TYPE, headers={"Cache-Control": "private, max-age=300"})
