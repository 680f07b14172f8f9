"""Alembic migrations: upgrade and downgrade on SQLite and PostgreSQL, the ORM models match the migrated
schema exactly, and the Alembic command line works from the repository."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import inspect

from server.db import (
    MIGRATIONS_DIR,
    alembic_config,
    current_revision,
    downgrade_database,
    load_models,
    upgrade_database,
)
from tests.server.conftest import BACKENDS, scratch_database

REPOSITORY = Path(__file__).resolve().parents[2]


@pytest.fixture(params=BACKENDS)
def scratch(request: pytest.FixtureRequest, tmp_path: Path):  # type: ignore[no-untyped-def]
    database = scratch_database(request.param, tmp_path)
    yield database
    database.drop()


def head_revision() -> str:
    return str(ScriptDirectory.from_config(alembic_config()).get_current_head())


def test_upgrade_creates_the_schema_and_downgrade_removes_it(scratch) -> None:  # type: ignore[no-untyped-def]
    upgrade_database(scratch.engine)
    assert current_revision(scratch.engine) == head_revision()
    tables = set(inspect(scratch.engine).get_table_names())
    assert set(load_models().tables) <= tables
    downgrade_database(scratch.engine, "base")
    assert set(inspect(scratch.engine).get_table_names()) <= {"alembic_version"}
    upgrade_database(scratch.engine)  # and back up again: the migrations are repeatable
    assert current_revision(scratch.engine) == head_revision()


def test_models_and_migrations_agree(scratch) -> None:  # type: ignore[no-untyped-def]
    upgrade_database(scratch.engine)
    with scratch.engine.connect() as connection:
        context = MigrationContext.configure(connection, opts={"compare_type": True})
        differences = compare_metadata(context, load_models())
    assert differences == []


def test_the_alembic_command_line_upgrades_from_the_settings(tmp_path: Path) -> None:
    environment = {**os.environ, "SSP_REHAB_DATABASE_URL": f"sqlite:///{tmp_path / 'cli.sqlite3'}"}
    command = [sys.executable, "-m", "alembic", "-c", str(MIGRATIONS_DIR / "alembic.ini"), "upgrade", "head"]
    result = subprocess.run(command, cwd=REPOSITORY, env=environment, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    current = subprocess.run(
        [*command[:-2], "current"], cwd=REPOSITORY, env=environment, capture_output=True, text=True, timeout=120
    )
    assert head_revision() in current.stdout
