"""Therapist notes of one run, SOAP-style (subjective, objective, assessment, plan)."""

from __future__ import annotations

import datetime as dt

from sqlalchemy import ForeignKey, Text
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base, UTCDateTime, utc_now


class RunNote(Base):
    __tablename__ = "run_notes"

    run_id: Mapped[int] = mapped_column(ForeignKey("session_runs.id", ondelete="CASCADE"), primary_key=True)
    subjective: Mapped[str] = mapped_column(Text, default="")
    objective: Mapped[str] = mapped_column(Text, default="")
    assessment: Mapped[str] = mapped_column(Text, default="")
    plan: Mapped[str] = mapped_column(Text, default="")
    author_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"), default=None)
    updated_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now, onupdate=utc_now)
