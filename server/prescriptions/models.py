"""Prescriptions and their immutable versions: editing adds a version, sessions keep the one they ran."""

from __future__ import annotations

import datetime as dt
from typing import Any

from sqlalchemy import JSON, ForeignKey, String, Text, UniqueConstraint
from sqlalchemy.orm import Mapped, mapped_column, relationship

from server.db import Base, UTCDateTime, utc_now


class Prescription(Base):
    __tablename__ = "prescriptions"

    id: Mapped[int] = mapped_column(primary_key=True)
    patient_id: Mapped[int] = mapped_column(ForeignKey("patients.id", ondelete="RESTRICT"), index=True)
    name: Mapped[str] = mapped_column(String(200))
    latest_version: Mapped[int] = mapped_column(default=1)
    created_by_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now)

    versions: Mapped[list[PrescriptionVersion]] = relationship(
        back_populates="prescription", order_by="PrescriptionVersion.version", lazy="selectin"
    )

    # Optimistic concurrency: a revision's UPDATE is `... WHERE latest_version = <the one read>`, so of two
    # revisions based on one version the second writes nothing (the service sets the new number itself).
    __mapper_args__ = {"version_id_col": latest_version, "version_id_generator": False}  # noqa: RUF012


class PrescriptionVersion(Base):
    __tablename__ = "prescription_versions"
    __table_args__ = (UniqueConstraint("prescription_id", "version", name="uq_prescription_versions_number"),)

    id: Mapped[int] = mapped_column(primary_key=True)
    prescription_id: Mapped[int] = mapped_column(ForeignKey("prescriptions.id", ondelete="CASCADE"))
    version: Mapped[int]
    content: Mapped[dict[str, Any]] = mapped_column(JSON)
    note: Mapped[str] = mapped_column(Text, default="")
    created_by_id: Mapped[int | None] = mapped_column(ForeignKey("users.id", ondelete="SET NULL"))
    created_at: Mapped[dt.datetime] = mapped_column(UTCDateTime, default=utc_now)

    prescription: Mapped[Prescription] = relationship(back_populates="versions")
