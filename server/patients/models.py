"""Patient records: identity, anthropometrics (SI) and the clinical context of balance training."""

from __future__ import annotations

import datetime as dt

from sqlalchemy import CheckConstraint, Date, Float, ForeignKey, String, Text, event
from sqlalchemy.orm import Mapped, mapped_column

from server.db import Base, UTCDateTime, utc_now
from server.patients.search import search_key

SEXES = ("female", "male", "other", "unknown")
AFFECTED_SIDES = ("left", "right", "both", "none")


class Patient(Base):
    __tablename__ = "patients"
    __table_args__ = (
        CheckConstraint("height_m > 0", name="height_positive"),
        CheckConstraint("body_mass_kg > 0", name="body_mass_positive"),
    )

    id: Mapped[int] = mapped_column(primary_key=True)
    identifier: Mapped[str] = mapped_column(String(64), unique=True)
    name: Mapped[str] = mapped_column(String(200))
    date_of_birth: Mapped[dt.date] = mapped_column(Date)
    sex: Mapped[str] = mapped_column(String(16))
    height_m: Mapped[float] = mapped_column(Float)
    body_mass_kg: Mapped[float] = mapped_column(Float)
    diagnosis: Mapped[str] = mapped_column(String(200), default="", index=True)
    affected_side: Mapped[str] = mapped_column(String(8), default="none")
    contraindications: Mapped[str] = mapped_column(Text, default="")
    notes: Mapped[str] = mapped_column(Text, default="")
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now)
    updated_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now, onupdate=utc_now)
    # Archived records leave the lists but stay whole: runs and prescriptions keep pointing at them.
    archived_at: Mapped[dt.datetime | None] = mapped_column(UTCDateTime, default=None)
    search_key: Mapped[str] = mapped_column(String(300), default="", index=True)
    # Optimistic concurrency (docs/service.md): every UPDATE is `... WHERE version = <the version read>`,
    # so of two changes based on one version the second touches no row and is refused (412).
    version: Mapped[int] = mapped_column(default=1, server_default="1")
    updated_by_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"), default=None)

    __mapper_args__ = {"version_id_col": version}  # noqa: RUF012 (SQLAlchemy reads it from the class)


class CareTeamMember(Base):
    """A clinician who may read and change one patient's record and everything hanging off it
    (docs/service.md, "Who may see and change what")."""

    __tablename__ = "care_team_members"

    patient_id: Mapped[int] = mapped_column(ForeignKey("patients.id", ondelete="CASCADE"), primary_key=True)
    user_id: Mapped[int] = mapped_column(ForeignKey("users.id", ondelete="CASCADE"), primary_key=True, index=True)
    added_by_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"), default=None)
    added_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now)


@event.listens_for(Patient, "before_insert")
@event.listens_for(Patient, "before_update")
def _refresh_search_key(_mapper: object, _connection: object, patient: Patient) -> None:
    patient.search_key = search_key(patient.name, patient.identifier)
