"""Scheduling service functions: bookings with conflict detection, recurring series, iCalendar feeds.

Two bookings conflict when their intervals [start, end) overlap and they share the robot or the patient;
cancelled bookings never conflict. The check and the insert happen in one transaction that holds a
booking lock (PostgreSQL: advisory locks per robot and patient; SQLite: the database write lock, which
every transaction takes up front), so two concurrent requests cannot both book the same slot.
"""

from __future__ import annotations

import datetime as dt
import zlib
from collections.abc import Iterable
from dataclasses import dataclass

from sqlalchemy import or_, select, text
from sqlalchemy.orm import Session

from server.audit import service as audit
from server.db import writes
from server.errors import ConflictError, InvalidFieldError, NotFoundError
from server.patients.models import Patient
from server.prescriptions import service as prescriptions
from server.prescriptions.models import PrescriptionVersion
from server.scheduling.models import ScheduledSession, ScheduleSeries
from server.scheduling.schemas import Recurrence, ScheduleCreate, ScheduledSessionOut, ScheduleUpdate
from server.users.models import User

STEP_DAYS = {"daily": 1, "weekly": 7}


@dataclass(frozen=True)
class Slot:
    robot: str
    patient_id: int
    start: dt.datetime
    end: dt.datetime


def to_out(booking: ScheduledSession, prescription_id: int, version: int) -> ScheduledSessionOut:
    return ScheduledSessionOut(
        id=booking.id,
        patient_id=booking.patient_id,
        prescription_id=prescription_id,
        prescription_version=version,
        prescription_version_id=booking.prescription_version_id,
        robot=booking.robot,
        therapist_id=booking.therapist_id,
        start=booking.start_utc,
        end=booking.end_utc,
        duration_s=booking.duration_s,
        status=booking.status,
        series_id=booking.series_id,
        notes=booking.notes,
    )


def booking_out(*, session: Session, booking: ScheduledSession) -> ScheduledSessionOut:
    version = session.get(PrescriptionVersion, booking.prescription_version_id)
    assert version is not None  # a foreign key guarantees it
    return to_out(booking, version.prescription_id, version.version)


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


def _first_conflict(session: Session, slot: Slot, ignore_ids: set[int]) -> ConflictError | None:
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
    return ConflictError(
        f"{what} already booked from {other.start_utc:%Y-%m-%d %H:%M} to {other.end_utc:%H:%M} UTC"
        f" (session {other.id}); requested {slot.start:%Y-%m-%d %H:%M} to {slot.end:%H:%M} UTC",
        field=field,
    )


def _check_free(session: Session, slots: list[Slot], ignore_ids: set[int]) -> None:
    _lock_bookings(session, slots)
    for index, slot in enumerate(slots):
        conflict = _first_conflict(session, slot, ignore_ids)
        if conflict is not None:
            if len(slots) > 1:
                conflict.args = (f"occurrence {index + 1} of {len(slots)}: {conflict.args[0]}",)
            raise conflict


def _occurrence_starts(start: dt.datetime, recurrence: Recurrence | None) -> list[dt.datetime]:
    if recurrence is None:
        return [start]
    step = dt.timedelta(days=STEP_DAYS[recurrence.frequency] * recurrence.interval)
    return [start + k * step for k in range(recurrence.count)]


@writes
def create_booking(*, session: Session, data: ScheduleCreate, actor_id: int) -> list[ScheduledSession]:
    """One booking, or one per occurrence of a recurring series: all of them or none."""
    if session.get(Patient, data.patient_id) is None:
        raise NotFoundError("patient", data.patient_id)
    version = _version_for(
        session, prescription_id=data.prescription_id, version=data.prescription_version, patient_id=data.patient_id
    )
    therapist_id = data.therapist_id or actor_id
    _therapist(session, therapist_id)
    duration = dt.timedelta(seconds=data.duration_s)
    start_utc = data.start.astimezone(dt.UTC)
    slots = [Slot(data.robot, data.patient_id, s, s + duration) for s in _occurrence_starts(start_utc, data.recurrence)]
    _check_free(session, slots, ignore_ids=set())
    series = None
    if data.recurrence is not None:
        series = ScheduleSeries(
            frequency=data.recurrence.frequency,
            interval=data.recurrence.interval,
            count=data.recurrence.count,
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
def update_booking(*, session: Session, session_id: int, data: ScheduleUpdate, actor_id: int) -> ScheduledSession:
    booking = get_booking(session=session, session_id=session_id)
    changes = data.model_dump(exclude_unset=True, exclude_none=True)
    if "therapist_id" in changes:
        _therapist(session, changes["therapist_id"])
        booking.therapist_id = changes["therapist_id"]
    if "prescription_version" in changes:
        current = session.get(PrescriptionVersion, booking.prescription_version_id)
        assert current is not None
        booking.prescription_version_id = prescriptions.get_version(
            session=session, prescription_id=current.prescription_id, version=changes["prescription_version"]
        ).id
    if "start" in changes:
        booking.start_utc = changes["start"].astimezone(dt.UTC)
    booking.duration_s = changes.get("duration_s", booking.duration_s)
    booking.end_utc = booking.start_utc + dt.timedelta(seconds=booking.duration_s)
    booking.robot = changes.get("robot", booking.robot)
    booking.status = changes.get("status", booking.status)
    booking.notes = changes.get("notes", booking.notes)
    if booking.status != "cancelled":
        _check_free(
            session, [Slot(booking.robot, booking.patient_id, booking.start_utc, booking.end_utc)], {booking.id}
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
    query = (
        # Only the version's numbers: its content (JSON) is not needed to list bookings.
        select(ScheduledSession, PrescriptionVersion.prescription_id, PrescriptionVersion.version)
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


def therapist_calendar(*, session: Session, therapist_id: int, product_id: str) -> bytes:
    """An iCalendar (RFC 5545) feed of the therapist's bookings. Patients appear by record number only,
    because calendar feeds are copied into calendar apps outside the clinic's control."""
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
    stamp = dt.datetime.now(dt.UTC)
    for booking, identifier in rows:
        event = Event()
        event.add("uid", f"scheduled-session-{booking.id}@ssp-rehab")
        event.add("dtstamp", stamp)
        event.add("dtstart", booking.start_utc)
        event.add("dtend", booking.end_utc)
        event.add("summary", f"Balance training {identifier} on {booking.robot}")
        event.add("location", booking.robot)
        event.add("status", "CANCELLED" if booking.status == "cancelled" else "CONFIRMED")
        calendar.add_component(event)
    return calendar.to_ical()
