"""Scheduled sessions: who trains, on which robot, when, with which prescription version; recurring series."""

from __future__ import annotations

import datetime as dt

from sqlalchemy import CheckConstraint, DateTime, ForeignKey, Index, String, Text
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base, UTCDateTime, utc_now

STATUSES = ("scheduled", "cancelled", "completed")
FREQUENCIES = ("daily", "weekly")


class ScheduleSeries(Base):
    __tablename__ = "schedule_series"

    id: Mapped[int] = mapped_column(primary_key=True)
    frequency: Mapped[str] = mapped_column(String(16))
    interval: Mapped[int] = mapped_column(default=1)
    count: Mapped[int]
    # The series is expanded in this zone from this wall time (RFC 5545 RRULE semantics), so that every
    # occurrence keeps it across daylight-saving changes. Null for series booked before migration 0003.
    timezone: Mapped[str | None] = mapped_column(String(64), default=None)
    first_start_local: Mapped[dt.datetime | None] = mapped_column(DateTime, default=None)
    created_by_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now)


class ScheduledSession(Base):
    __tablename__ = "scheduled_sessions"
    __table_args__ = (
        CheckConstraint("duration_s > 0", name="duration_positive"),
        CheckConstraint("status IN ('scheduled', 'cancelled', 'completed')", name="status"),
        Index("ix_scheduled_sessions_robot_start", "robot", "start_utc"),
        Index("ix_scheduled_sessions_patient_start", "patient_id", "start_utc"),
        Index("ix_scheduled_sessions_therapist_start", "therapist_id", "start_utc"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    patient_id: Mapped[int] = mapped_column(ForeignKey("patients.id", ondelete="RESTRICT"))
    prescription_version_id: Mapped[int] = mapped_column(ForeignKey("prescription_versions.id", ondelete="RESTRICT"))
    robot: Mapped[str] = mapped_column(String(64))
    therapist_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="RESTRICT"))
    start_utc: Mapped[dt.datetime] = mapped_column(UTCDateTime)
    end_utc: Mapped[dt.datetime] = mapped_column(UTCDateTime)
    duration_s: Mapped[int]
    status: Mapped[str] = mapped_column(String(16), default="scheduled")
    series_id: Mapped[int | None] = mapped_column(ForeignKey("schedule_series.id", ondelete="SET NULL"), index=True)
    notes: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now)


class CalendarToken(Base):
    """A therapist's calendar-subscription secret (its SHA-256 only); deleting the row revokes the link."""

    __tablename__ = "calendar_tokens"

    therapist_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), primary_key=True)
    token_sha256: Mapped[str] = mapped_column(String(64), unique=True)
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now)
