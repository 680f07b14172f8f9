"""Care teams and patient versions (issue 20, defects 14 and 15): who may see and change a patient's record
(`care_team_members`), and a version per patient record for optimistic concurrency (`If-Match`).

Existing records get the care team their history shows: the clinician who created the record (audit log),
who booked or was booked for the patient, and who wrote one of the patient's prescriptions. Admins need no
membership. A record with none of these is seen by admins only until an admin adds its therapists.

Revision ID: 0006
Revises: 0005
Create Date: 2026-12-02 05:00:00
"""

from __future__ import annotations

import datetime as dt

import sqlalchemy as sa
from alembic import op

revision: str = "0006"
down_revision: str | None = "0005"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    with op.batch_alter_table("patients", schema=None) as batch_op:
        batch_op.add_column(sa.Column("version", sa.Integer(), nullable=False, server_default="1"))
        batch_op.add_column(sa.Column("updated_by_id", sa.Integer(), nullable=True))
        batch_op.create_foreign_key(
            batch_op.f("fk_patients_updated_by_id_users"), "users", ["updated_by_id"], ["id"], ondelete="SET NULL"
        )
    op.create_table(
        "care_team_members",
        sa.Column("patient_id", sa.Integer(), nullable=False),
        sa.Column("user_id", sa.Integer(), nullable=False),
        sa.Column("added_by_id", sa.Integer(), nullable=True),
        sa.Column("added_at", sa.DateTime(), nullable=False),
        sa.ForeignKeyConstraint(["patient_id"], ["patients.id"], name=op.f("fk_care_team_members_patient_id_patients"),
                                ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["user_id"], ["users.id"], name=op.f("fk_care_team_members_user_id_users"),
                                ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["added_by_id"], ["users.id"], name=op.f("fk_care_team_members_added_by_id_users"),
                                ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("patient_id", "user_id", name=op.f("pk_care_team_members")),
    )  # fmt: skip
    op.create_index(op.f("ix_care_team_members_user_id"), "care_team_members", ["user_id"], unique=False)
    _backfill_care_teams()


def _backfill_care_teams() -> None:
    connection = op.get_bind()
    pairs: set[tuple[int, int]] = set()
    for query in (
        "SELECT resource_id, user_id FROM audit_log WHERE resource_type = 'patient' AND action = 'create'"
        " AND resource_id IS NOT NULL AND user_id IS NOT NULL",
        "SELECT patient_id, therapist_id FROM scheduled_sessions",
        "SELECT patient_id, created_by_id FROM prescriptions WHERE created_by_id IS NOT NULL",
    ):
        pairs.update((int(p), int(u)) for p, u in connection.execute(sa.text(query)).all())
    patients = {int(row[0]) for row in connection.execute(sa.text("SELECT id FROM patients")).all()}
    users = {int(row[0]) for row in connection.execute(sa.text("SELECT id FROM users")).all()}
    members = sa.table(
        "care_team_members", sa.column("patient_id", sa.Integer), sa.column("user_id", sa.Integer),
        sa.column("added_by_id", sa.Integer), sa.column("added_at", sa.DateTime),
    )  # fmt: skip
    now = dt.datetime.now(dt.UTC).replace(tzinfo=None)
    rows = [
        {"patient_id": p, "user_id": u, "added_by_id": None, "added_at": now}
        for p, u in sorted(pairs)
        if p in patients and u in users
    ]
    if rows:
        connection.execute(members.insert(), rows)


def downgrade() -> None:
    op.drop_index(op.f("ix_care_team_members_user_id"), table_name="care_team_members")
    op.drop_table("care_team_members")
    with op.batch_alter_table("patients", schema=None) as batch_op:
        batch_op.drop_constraint(batch_op.f("fk_patients_updated_by_id_users"), type_="foreignkey")
        batch_op.drop_column("updated_by_id")
        batch_op.drop_column("version")
