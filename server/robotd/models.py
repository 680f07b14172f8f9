"""Session runs, their events and the durable telemetry log (chunks of the worker's telemetry records)."""

from __future__ import annotations

import datetime as dt
import enum
from typing import Any

from sqlalchemy import JSON, BigInteger, Float, ForeignKey, Index, LargeBinary, String, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base, UTCDateTime, utc_now


class RunState(enum.StrEnum):
    """A run's state: only the robot daemon changes it (server.robotd), and only `end_run` ends it."""

    RUNNING = "running"
    PAUSED = "paused"
    ENDED = "ended"


class RunOutcome(enum.StrEnum):
    """Why a run ended."""

    COMPLETED = "completed"
    STOPPED = "stopped"  # by the operator's stop command
    EMERGENCY_STOP = "emergency_stop"
    FAULT = "fault"
    FALL = "fall"
    LIMIT_HIT = "limit_hit"
    INTERRUPTED = "interrupted"  # the console, the daemon or the worker was lost while it ran


ACTIVE_STATES = (RunState.RUNNING, RunState.PAUSED)
RUN_STATES = tuple(state.value for state in RunState)


class SessionRun(Base):
    __tablename__ = "session_runs"

    id: Mapped[int] = mapped_column(primary_key=True)
    scheduled_session_id: Mapped[int] = mapped_column(
        ForeignKey("scheduled_sessions.id", ondelete="RESTRICT"), index=True
    )
    prescription_version_id: Mapped[int] = mapped_column(ForeignKey("prescription_versions.id", ondelete="RESTRICT"))
    robot: Mapped[str] = mapped_column(String(64))
    state: Mapped[str] = mapped_column(String(16), default="running")
    outcome: Mapped[str | None] = mapped_column(String(32), default=None)
    started_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now, index=True)
    ended_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, default=None)
    started_by_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    stopped_by_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    sample_count: Mapped[int] = mapped_column(BigInteger, default=0)


class SessionEvent(Base):
    __tablename__ = "session_events"
    __table_args__ = (Index("ix_session_events_run_utc", "run_id", "utc"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    run_id: Mapped[int | None] = mapped_column(ForeignKey("session_runs.id", ondelete="CASCADE"))
    kind: Mapped[str] = mapped_column(String(32))
    tick: Mapped[int | None] = mapped_column(BigInteger, default=None)
    tick_time_s: Mapped[float | None] = mapped_column(Float, default=None)
    utc: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now)
    detector: Mapped[str | None] = mapped_column(String(64), default=None)
    details: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    user_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))


class TelemetryChunk(Base):
    """`data` is one `.npy` blob of the worker's structured telemetry records: it carries its own dtype."""

    __tablename__ = "telemetry_chunks"
    __table_args__ = (UniqueConstraint("run_id", "sequence", name="uq_telemetry_chunks_run_sequence"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    run_id: Mapped[int] = mapped_column(ForeignKey("session_runs.id", ondelete="CASCADE"))
    sequence: Mapped[int]
    first_tick: Mapped[int] = mapped_column(BigInteger)
    sample_count: Mapped[int]
    data: Mapped[bytes] = mapped_column(LargeBinary)
