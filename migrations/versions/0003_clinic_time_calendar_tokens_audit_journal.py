"""Clinic-local time for series, calendar subscription tokens, and journal ids in the audit log.

- `schedule_series.timezone` and `.first_start_local`: the zone a series is expanded in and the wall time
  its occurrences keep. Existing series get the clinic zone (SSP_REHAB_TIMEZONE, else the machine's) and
  the local wall time of their first booking. Their bookings are left where they are: patients were told
  those times, and a booking the old code shifted by an hour is for the clinic to move, not a migration.
- `calendar_tokens`: one revocable calendar-subscription secret (SHA-256) per therapist.
- `audit_log.journal_id`: unique, so that a replayed audit-journal line is inserted once.

Revision ID: 0003
Revises: 0002
Create Date: 2026-12-01 10:00:00
"""

from __future__ import annotations

import datetime as dt
from zoneinfo import ZoneInfo

import sqlalchemy as sa
from alembic import op

revision: str = "0003"
down_revision: str | None = "0002"
branch_labels: str | None = None
depends_on: str | None = None


def _clinic_zone() -> ZoneInfo:
    from server.settings import Settings

    return Settings().clinic_zone()


def upgrade() -> None:
    with op.batch_alter_table("schedule_series", schema=None) as batch_op:
        batch_op.add_column(sa.Column("timezone", sa.String(length=64), nullable=True))
        batch_op.add_column(sa.Column("first_start_local", sa.DateTime(), nullable=True))
    connection = op.get_bind()
    first_starts = connection.execute(
        sa.text(
            "SELECT series_id, MIN(start_utc) FROM scheduled_sessions WHERE series_id IS NOT NULL GROUP BY series_id"
        )
    ).all()
    if first_starts:
        zone = _clinic_zone()
        for series_id, first_start in first_starts:
            if isinstance(first_start, str):  # SQLite hands back text for an aggregate
                first_start = dt.datetime.fromisoformat(first_start)
            local = first_start.replace(tzinfo=dt.UTC).astimezone(zone).replace(tzinfo=None)
            connection.execute(
                sa.text("UPDATE schedule_series SET timezone = :zone, first_start_local = :local WHERE id = :id"),
                {"zone": zone.key, "local": local, "id": series_id},
            )

    op.create_table(
        "calendar_tokens",
        sa.Column("therapist_id", sa.Integer(), nullable=False),
        sa.Column("token_sha256", sa.String(length=64), nullable=False),
        sa.Column("created_at", sa.DateTime(), nullable=False),
        sa.ForeignKeyConstraint(
            ["therapist_id"], ["users.id"], name=op.f("fk_calendar_tokens_therapist_id_users"), ondelete="CASCADE"
        ),
        sa.PrimaryKeyConstraint("therapist_id", name=op.f("pk_calendar_tokens")),
        sa.UniqueConstraint("token_sha256", name=op.f("uq_calendar_tokens_token_sha256")),
    )

    with op.batch_alter_table("audit_log", schema=None) as batch_op:
        batch_op.add_column(sa.Column("journal_id", sa.String(length=32), nullable=True))
        batch_op.create_unique_constraint(batch_op.f("uq_audit_log_journal_id"), ["journal_id"])


def downgrade() -> None:
    with op.batch_alter_table("audit_log", schema=None) as batch_op:
        batch_op.drop_constraint(batch_op.f("uq_audit_log_journal_id"), type_="unique")
        batch_op.drop_column("journal_id")
    op.drop_table("calendar_tokens")
    with op.batch_alter_table("schedule_series", schema=None) as batch_op:
        batch_op.drop_column("first_start_local")
        batch_op.drop_column("timezone")
