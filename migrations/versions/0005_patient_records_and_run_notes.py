"""Patient records and run notes (issue 16): patients can be archived and are found by an accent-folded
search key ("Jurgen" finds "Jürgen" on SQLite and PostgreSQL alike); each run gets SOAP notes.

Revision ID: 0005
Revises: 0003
Create Date: 2026-12-01 09:45:00
"""

from __future__ import annotations

import sqlalchemy as sa
from alembic import op

from server.patients.search import search_key

revision: str = "0005"
down_revision: str | None = "0003"
branch_labels: str | None = None
depends_on: str | None = None


def upgrade() -> None:
    with op.batch_alter_table("patients", schema=None) as batch_op:
        batch_op.add_column(sa.Column("archived_at", sa.DateTime(), nullable=True))
        batch_op.add_column(sa.Column("search_key", sa.String(length=300), nullable=False, server_default=""))
        batch_op.create_index(batch_op.f("ix_patients_search_key"), ["search_key"], unique=False)
    patients = sa.table(
        "patients", sa.column("id", sa.Integer), sa.column("name", sa.String), sa.column("identifier", sa.String),
        sa.column("search_key", sa.String),
    )  # fmt: skip
    connection = op.get_bind()
    for row in connection.execute(sa.select(patients.c.id, patients.c.name, patients.c.identifier)).all():
        connection.execute(
            patients.update().where(patients.c.id == row.id).values(search_key=search_key(row.name, row.identifier))
        )
    op.create_table(
        "run_notes",
        sa.Column("run_id", sa.Integer(), nullable=False),
        sa.Column("subjective", sa.Text(), nullable=False),
        sa.Column("objective", sa.Text(), nullable=False),
        sa.Column("assessment", sa.Text(), nullable=False),
        sa.Column("plan", sa.Text(), nullable=False),
        sa.Column("author_id", sa.Integer(), nullable=True),
        sa.Column("updated_at", sa.DateTime(), nullable=False),
        sa.ForeignKeyConstraint(["run_id"], ["session_runs.id"], name=op.f("fk_run_notes_run_id_session_runs"),
                                ondelete="CASCADE"),
        sa.ForeignKeyConstraint(["author_id"], ["users.id"], name=op.f("fk_run_notes_author_id_users"),
                                ondelete="SET NULL"),
        sa.PrimaryKeyConstraint("run_id", name=op.f("pk_run_notes")),
    )  # fmt: skip


def downgrade() -> None:
    op.drop_table("run_notes")
    with op.batch_alter_table("patients", schema=None) as batch_op:
        batch_op.drop_index(batch_op.f("ix_patients_search_key"))
        batch_op.drop_column("search_key")
        batch_op.drop_column("archived_at")
