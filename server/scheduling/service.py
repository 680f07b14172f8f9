"""Scheduling service functions: bookings with conflict detection, recurring series, iCalendar feeds.

Two bookings conflict when their intervals [start, end) overlap and they share the robot or the patient;
cancelled bookings never conflict. The check and the insert happen in one transaction that holds a
booking lock (PostgreSQL: advisory locks per robot and patient; SQLite: the database write lock, which
every transaction takes up front), so two concurrent requests cannot both book the same slot.

Times: stored in UTC, expanded and answered in the clinic's zone (`server.scheduling.clinic_time`), so
that a series keeps its wall-clock time across daylight-saving changes. Every function that reads or
writes times takes that zone as `zone=`.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import secrets
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any
from zoneinfo import ZoneInfo

from sqlalchemy import Select, func, or_, select, text
from sqlalchemy.orm import Session

from server.audit import service as audit
from server.db import writes
from server.errors import ConflictError, InvalidFieldError, NotFoundError
from server.patients.models import Patient
from server.patients.service import join_care_team
from server.prescriptions import service as prescriptions
from server.prescriptions.models import PrescriptionVersion
from server.robotd.models import SessionRun
from server.scheduling import clinic_time
from server.scheduling.models import CalendarToken, ScheduledSession, ScheduleSeries
from server.scheduling.schemas import ScheduleCreate, ScheduledSessionOut, ScheduleUpdate, WeekOut
from server.users.models import User


@dataclass(frozen=True)
class Slot:
    robot: str
    patient_id: int
    start: dt.datetime
    end: dt.datetime


def _out_fields(booking: ScheduledSession, prescription_id: int, version: int, zone: ZoneInfo) -> dict[str, object]:
    return dict(
        id=booking.id,
        patient_id=booking.patient_id,
        prescription_id=prescription_id,
        prescription_version=version,
        prescription_version_id=booking.prescription_version_id,
        robot=booking.robot,
        therapist_id=booking.therapist_id,
        start=booking.start_utc,
        end=booking.end_utc,
        start_local=booking.start_utc.astimezone(zone),
        end_local=booking.end_utc.astimezone(zone),
        timezone=zone.key,
        duration_s=booking.duration_s,
        status=booking.status,
        series_id=booking.series_id,
        notes=booking.notes,
    )


def to_out(booking: ScheduledSession, prescription_id: int, version: int, zone: ZoneInfo) -> ScheduledSessionOut:
    return ScheduledSessionOut.model_validate(_out_fields(booking, prescription_id, version, zone))


def booking_out(*, session: Session, booking: ScheduledSession, zone: ZoneInfo) -> ScheduledSessionOut:
    version = session.get(PrescriptionVersion, booking.prescription_version_id)
    assert version is not None  # a foreign key guarantees it
    return to_out(booking, version.prescription_id, version.version, zone)


def get_booking(*, session: Session, session_id: int) -> ScheduledSession:
    booking = session.get(ScheduledSession, session_id)
    if booking is None:
        raise NotFoundError("session", session_id)
    return booking


def _therapist(session: Session, therapist_id: int) -> User:
    therapist = session.get(User, therapist_id)
    if therapist is None:
        raise NotFoundError("user", therapist_id)
    if not therapist.is_active:
        raise InvalidFieldError("therapist_id", therapist_id, "must be an active account")
    return therapist


def _version_for(
    session: Session, *, prescription_id: int, version: int | None, patient_id: int
) -> PrescriptionVersion:
    prescription = prescriptions.get_prescription(session=session, prescription_id=prescription_id)
    if prescription.patient_id != patient_id:
        raise InvalidFieldError("prescription_id", prescription_id, f"belongs to another patient, not {patient_id}")
    return prescriptions.get_version(
        session=session, prescription_id=prescription_id, version=version or prescription.latest_version
    )


def _lock_bookings(session: Session, slots: Iterable[Slot]) -> None:
    if session.get_bind().dialect.name != "postgresql":
        return  # SQLite: BEGIN IMMEDIATE already serialises writers (server.db)
    keys = sorted({f"robot:{s.robot}" for s in slots} | {f"patient:{s.patient_id}" for s in slots})
    for key in keys:  # sorted, so that two requests never wait on each other's locks
        session.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": zlib.crc32(key.encode())})


def _first_conflict(session: Session, slot: Slot, ignore_ids: set[int], zone: ZoneInfo) -> ConflictError | None:
    query = (
        select(ScheduledSession)
        .where(
            ScheduledSession.status != "cancelled",
            ScheduledSession.start_utc < slot.end,
            ScheduledSession.end_utc > slot.start,
            or_(ScheduledSession.robot == slot.robot, ScheduledSession.patient_id == slot.patient_id),
        )
        .order_by(ScheduledSession.start_utc)
        .limit(1)
    )
    if ignore_ids:
        query = query.where(ScheduledSession.id.not_in(ignore_ids))
    other = session.scalar(query)
    if other is None:
        return None
    what, field = ("robot", "robot") if other.robot == slot.robot else ("patient", "patient_id")

    def span(start: dt.datetime, end: dt.datetime) -> str:  # in the clinic's wall time, as the week shows it
        return f"{start.astimezone(zone):%Y-%m-%d %H:%M} to {end.astimezone(zone):%H:%M}"

    return ConflictError(
        f"{what} already booked from {span(other.start_utc, other.end_utc)} (session {other.id});"
        f" requested {span(slot.start, slot.end)} ({zone.key} time)",
        field=field,
    )


def _check_free(session: Session, slots: list[Slot], ignore_ids: set[int], zone: ZoneInfo) -> None:
    _lock_bookings(session, slots)
    for index, slot in enumerate(slots):
        conflict = _first_conflict(session, slot, ignore_ids, zone)
        if conflict is not None:
            if len(slots) > 1:
                conflict.args = (f"occurrence {index + 1} of {len(slots)}: {conflict.args[0]}",)
            raise conflict


def _requested_start(
    start: dt.datetime | None, start_local: dt.datetime | None, zone: ZoneInfo
) -> tuple[dt.datetime, dt.datetime]:
    """(UTC, clinic-local wall time) of a requested start; refused if that wall time is in a gap or overlap."""
    if start_local is not None:
        return clinic_time.to_utc(start_local, zone, field="start_local"), start_local
    assert start is not None
    return start.astimezone(dt.UTC), clinic_time.wall_time(start, zone, field="start")


@writes
def create_booking(*, session: Session, data: ScheduleCreate, actor_id: int, zone: ZoneInfo) -> list[ScheduledSession]:
    """One booking, or one per occurrence of a recurring series (expanded in the clinic's local time, so
    each keeps the first one's wall-clock time): all of them or none."""
    if session.get(Patient, data.patient_id) is None:
        raise NotFoundError("patient", data.patient_id)
    version = _version_for(
        session, prescription_id=data.prescription_id, version=data.prescription_version, patient_id=data.patient_id
    )
    therapist_id = data.therapist_id or actor_id
    _therapist(session, therapist_id)
    duration = dt.timedelta(seconds=data.duration_s)
    start_utc, first_local = _requested_start(data.start, data.start_local, zone)
    recurrence = data.recurrence
    starts = (
        [start_utc]
        if recurrence is None
        else clinic_time.local_occurrences(
            first_local, recurrence.frequency, recurrence.interval, recurrence.count, zone, field="recurrence"
        )
    )
    slots = [Slot(data.robot, data.patient_id, s, s + duration) for s in starts]
    _check_free(session, slots, ignore_ids=set(), zone=zone)
    series = None
    if recurrence is not None:
        series = ScheduleSeries(
            frequency=recurrence.frequency,
            interval=recurrence.interval,
            count=recurrence.count,
            timezone=zone.key,
            first_start_local=first_local,
            created_by_id=actor_id,
        )
        session.add(series)
        session.flush()
    bookings = [
        ScheduledSession(
            patient_id=data.patient_id,
            prescription_version_id=version.id,
            robot=data.robot,
            therapist_id=therapist_id,
            start_utc=slot.start,
            end_utc=slot.end,
            duration_s=data.duration_s,
            series_id=series.id if series else None,
            notes=data.notes,
        )
        for slot in slots
    ]
    session.add_all(bookings)
    session.flush()
    # The booked therapist treats the patient, so joins the care team (a booking for a colleague hands over).
    join_care_team(
        session=session, patient_id=data.patient_id, user_id=therapist_id, actor_id=actor_id, reason="booked"
    )
    for booking in bookings:
        audit.record(
            session=session,
            user_id=actor_id,
            action="create",
            resource_type="scheduled_session",
            resource_id=booking.id,
            details={"patient_id": data.patient_id},
        )
    return bookings


@writes
def update_booking(
    *, session: Session, session_id: int, data: ScheduleUpdate, actor_id: int, zone: ZoneInfo
) -> ScheduledSession:
    booking = get_booking(session=session, session_id=session_id)
    changes = data.model_dump(exclude_unset=True, exclude_none=True)
    if "therapist_id" in changes:
        _therapist(session, changes["therapist_id"])
        booking.therapist_id = changes["therapist_id"]
        join_care_team(
            session=session, patient_id=booking.patient_id, user_id=booking.therapist_id, actor_id=actor_id,
            reason="booked",
        )  # fmt: skip
    if "prescription_version" in changes:
        current = session.get(PrescriptionVersion, booking.prescription_version_id)
        assert current is not None
        booking.prescription_version_id = prescriptions.get_version(
            session=session, prescription_id=current.prescription_id, version=changes["prescription_version"]
        ).id
    if "start" in changes or "start_local" in changes:
        booking.start_utc, _ = _requested_start(changes.get("start"), changes.get("start_local"), zone)
    booking.duration_s = changes.get("duration_s", booking.duration_s)
    booking.end_utc = booking.start_utc + dt.timedelta(seconds=booking.duration_s)
    booking.robot = changes.get("robot", booking.robot)
    booking.status = changes.get("status", booking.status)
    booking.notes = changes.get("notes", booking.notes)
    if booking.status != "cancelled":
        _check_free(
            session, [Slot(booking.robot, booking.patient_id, booking.start_utc, booking.end_utc)], {booking.id}, zone
        )
    audit.record(
        session=session,
        user_id=actor_id,
        action="update",
        resource_type="scheduled_session",
        resource_id=booking.id,
        details={"patient_id": booking.patient_id, "fields": sorted(changes)},
    )
    return booking


@writes
def cancel_series(*, session: Session, series_id: int, actor_id: int) -> list[ScheduledSession]:
    """Cancels the series' bookings that are still scheduled; past and completed ones stay as they are."""
    if session.get(ScheduleSeries, series_id) is None:
        raise NotFoundError("series", series_id)
    bookings = list(
        session.scalars(
            select(ScheduledSession).where(
                ScheduledSession.series_id == series_id, ScheduledSession.status == "scheduled"
            )
        )
    )
    for booking in bookings:
        booking.status = "cancelled"
    audit.record(
        session=session,
        user_id=actor_id,
        action="cancel",
        resource_type="schedule_series",
        resource_id=series_id,
        details={"session_ids": [b.id for b in bookings]},
    )
    return bookings


def list_bookings(
    *,
    session: Session,
    actor: User,
    start: dt.datetime | None = None,
    end: dt.datetime | None = None,
    robot: str | None = None,
    patient_id: int | None = None,
    therapist_id: int | None = None,
    status: str | None = None,
    limit: int = 100,
    offset: int = 0,
) -> list[tuple[ScheduledSession, int, int]]:
    """Bookings overlapping [start, end), earliest first, with their prescription id and version number."""
    from server.auth.access import restrict_to_care

    query = (
        # Only the version's numbers: its content (JSON) is not needed to list bookings.
        restrict_to_care(
            select(ScheduledSession, PrescriptionVersion.prescription_id, PrescriptionVersion.version),
            ScheduledSession.patient_id,
            actor,
        )
        .join(PrescriptionVersion, PrescriptionVersion.id == ScheduledSession.prescription_version_id)
        .order_by(ScheduledSession.start_utc, ScheduledSession.id)
        .limit(limit)
        .offset(offset)
    )
    if start is not None:
        query = query.where(ScheduledSession.end_utc > start)
    if end is not None:
        query = query.where(ScheduledSession.start_utc < end)
    for column, value in (
        (ScheduledSession.robot, robot),
        (ScheduledSession.patient_id, patient_id),
        (ScheduledSession.therapist_id, therapist_id),
        (ScheduledSession.status, status),
    ):
        if value is not None:
            query = query.where(column == value)
    return [
        (booking, prescription_id, version) for booking, prescription_id, version in session.execute(query).tuples()
    ]


def therapist_calendar(*, session: Session, therapist_id: int, product_id: str, zone: ZoneInfo) -> bytes:
    """An iCalendar (RFC 5545) feed of the therapist's bookings, in the clinic's zone (TZID, with its
    VTIMEZONE), so that calendar apps keep them at their wall-clock time. Patients appear by record
    number only, because calendar feeds are copied into calendar apps outside the clinic's control."""
    from icalendar import Calendar, Event

    therapist = session.get(User, therapist_id)
    if therapist is None:
        raise NotFoundError("user", therapist_id)
    rows = session.execute(
        select(ScheduledSession, Patient.identifier)
        .join(Patient, Patient.id == ScheduledSession.patient_id)
        .where(ScheduledSession.therapist_id == therapist_id)
        .order_by(ScheduledSession.start_utc)
    ).tuples()
    calendar = Calendar()
    calendar.add("prodid", product_id)
    calendar.add("version", "2.0")
    calendar.add("x-wr-calname", f"Balance training: {therapist.username}")
    calendar.add("x-wr-timezone", zone.key)
    stamp = dt.datetime.now(dt.UTC)
    for booking, identifier in rows:
        event = Event()
        event.add("uid", f"scheduled-session-{booking.id}@ssp-rehab")
        event.add("dtstamp", stamp)
        event.add("dtstart", booking.start_utc.astimezone(zone))
        event.add("dtend", booking.end_utc.astimezone(zone))
        event.add("summary", f"Balance training {identifier} on {booking.robot}")
        event.add("location", booking.robot)
        event.add("status", "CANCELLED" if booking.status == "cancelled" else "CONFIRMED")
        calendar.add_component(event)
    calendar.add_missing_timezones()
    return bytes(calendar.to_ical())


# --- calendar subscriptions: a secret link per therapist, for calendar apps that cannot log in ----------


def _token_digest(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


@writes
def issue_calendar_token(*, session: Session, therapist_id: int, actor_id: int) -> str:
    """A new subscription token for the therapist's feed; it replaces (revokes) any earlier one. Only its
    SHA-256 is stored, so the database never holds a usable link."""
    _therapist(session, therapist_id)
    token = secrets.token_urlsafe(32)
    existing = session.get(CalendarToken, therapist_id)
    if existing is None:
        session.add(CalendarToken(therapist_id=therapist_id, token_sha256=_token_digest(token)))
    else:
        existing.token_sha256 = _token_digest(token)
        existing.created_at = dt.datetime.now(dt.UTC)
    audit.record(
        session=session, user_id=actor_id, action="issue", resource_type="calendar_token", resource_id=therapist_id
    )
    return token


@writes
def revoke_calendar_token(*, session: Session, therapist_id: int, actor_id: int) -> None:
    existing = session.get(CalendarToken, therapist_id)
    if existing is None:
        raise NotFoundError("calendar subscription of user", therapist_id)
    session.delete(existing)
    audit.record(
        session=session, user_id=actor_id, action="revoke", resource_type="calendar_token", resource_id=therapist_id
    )


def therapist_for_calendar_token(*, session: Session, token: str) -> int | None:
    """The therapist whose live subscription token this is, or None (unknown or revoked)."""
    therapist_id = session.scalar(
        select(CalendarToken.therapist_id).where(CalendarToken.token_sha256 == _token_digest(token))
    )
    return int(therapist_id) if therapist_id is not None else None


def calendar_token_issued_at(*, session: Session, therapist_id: int) -> dt.datetime | None:
    token = session.get(CalendarToken, therapist_id)
    return token.created_at if token is not None else None


# --- the week view: one clinic-local week, with what the page shows, in one query ------------------------


def week_query(start: dt.datetime, end: dt.datetime, robot: str | None = None) -> Select[Any]:
    """Bookings starting in [start, end), with prescription numbers, patient name and record number, and
    the run count and last run outcome: one query for the whole week view."""
    runs = (
        select(
            SessionRun.scheduled_session_id.label("booking_id"),
            func.count(SessionRun.id).label("run_count"),
            func.max(SessionRun.id).label("last_run_id"),
        )
        .group_by(SessionRun.scheduled_session_id)
        .subquery()
    )
    last_run = SessionRun.__table__.alias("last_run")
    query = (
        select(
            ScheduledSession,
            PrescriptionVersion.prescription_id,
            PrescriptionVersion.version,
            Patient.name,
            Patient.identifier,
            func.coalesce(runs.c.run_count, 0),
            func.coalesce(last_run.c.outcome, last_run.c.state),
        )
        .join(PrescriptionVersion, PrescriptionVersion.id == ScheduledSession.prescription_version_id)
        .join(Patient, Patient.id == ScheduledSession.patient_id)
        .outerjoin(runs, runs.c.booking_id == ScheduledSession.id)
        .outerjoin(last_run, last_run.c.id == runs.c.last_run_id)
        .where(ScheduledSession.start_utc >= start, ScheduledSession.start_utc < end)
        .order_by(ScheduledSession.start_utc, ScheduledSession.id)
    )
    return query if robot is None else query.where(ScheduledSession.robot == robot)


def _busy_only(booking: dict[str, Any]) -> dict[str, Any]:
    """A booking of a patient outside the caller's care: when the robot and the therapist are busy, no more."""
    return {
        **booking, "patient_name": "", "patient_identifier": "", "notes": "", "run_count": 0,
        "last_run_outcome": None, "in_care": False,
    }  # fmt: skip


def week(
    *,
    session: Session,
    day: dt.date,
    zone: ZoneInfo,
    robot: str | None = None,
    shown: Callable[[set[int]], set[int]] | None = None,
) -> WeekOut:
    """Bookings starting in the clinic-local week holding `day`, with patient names and run summaries;
    `shown` picks the patients whose names, notes and runs the caller may see (the rest: free/busy only)."""
    start_local, end_local = clinic_time.week_bounds(day, zone)
    query = week_query(start_local, end_local, robot)
    bookings = [
        {
            **_out_fields(booking, prescription_id, version, zone),
            "patient_name": name,
            "patient_identifier": identifier,
            "run_count": run_count,
            "last_run_outcome": last_outcome,
        }
        for booking, prescription_id, version, name, identifier, run_count, last_outcome in session.execute(query)
    ]
    if shown is not None:
        in_care = shown({b["patient_id"] for b in bookings})
        bookings = [b if b["patient_id"] in in_care else _busy_only(b) for b in bookings]
    monday = start_local.date()
    # One validation of the whole week (in pydantic-core), not one Python call per booking.
    return WeekOut.model_validate(
        {
            "timezone": zone.key,
            "start_local": start_local,
            "end_local": end_local,
            "previous_week": monday - dt.timedelta(days=7),
            "next_week": monday + dt.timedelta(days=7),
            "bookings": bookings,
        }
    )
