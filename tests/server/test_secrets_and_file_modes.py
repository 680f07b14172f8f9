"""No secret in any message, and the data directory readable by its owner only (issue 20, defect 13 /
Build 10): `create-user` never prints the password it refuses and asks again when a person is typing; the
SQLite database, the token key and the journals are created (or tightened at start) owner-only."""

from __future__ import annotations

import logging
import os
import stat
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from server.app import create_app
from server.cli import service_commands
from server.cli.main import app as cli
from server.settings import Settings
from tests.server.conftest import TEST_SECRET

WEAK = "admin"  # shorter than the 8 characters an account's password needs
STRONG = "long-enough-pass"


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_create_user_refuses_a_weak_password_without_showing_it_when_nobody_types(tmp_path: Path) -> None:
    args = ["create-user", "--username", "chief", "--role", "admin", "--data-dir", str(tmp_path)]
    result = CliRunner().invoke(cli, [*args, "--password", WEAK])
    assert result.exit_code != 0
    assert "password" in result.output and "8" in result.output, result.output
    assert f"'{WEAK}'" not in result.output and f"= {WEAK}" not in result.output, result.output
    as_json = CliRunner().invoke(cli, [*args, "--password", WEAK, "--json"])
    assert as_json.exit_code != 0 and f"'{WEAK}'" not in as_json.output, as_json.output


def test_create_user_asks_again_for_a_weak_password_when_a_person_types(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(service_commands, "_interactive", lambda: True)
    args = ["create-user", "--username", "chief", "--role", "admin", "--data-dir", str(tmp_path)]
    typed = f"{WEAK}\n{WEAK}\n{STRONG}\n{STRONG}\n"
    result = CliRunner().invoke(cli, args, input=typed)
    assert result.exit_code == 0, result.output
    assert "at least 8 characters" in result.output and "created admin account" in result.output
    assert f"'{WEAK}'" not in result.output
    settings = Settings(_env_file=None, data_dir=tmp_path, secret_key=TEST_SECRET, start_worker=False)  # type: ignore[call-arg]
    with TestClient(create_app(settings)) as client:
        login = client.post("/api/v1/auth/login", json={"username": "chief", "password": STRONG})
        assert login.status_code == 200, login.text


@pytest.mark.parametrize("field", ["password", "new_password", "api_key", "refresh_token", "client_secret"])
def test_a_refusal_never_shows_a_secret_fields_value(field: str) -> None:
    from server.security import safe_validation_errors, shown_value

    assert "hunter2-secret" not in shown_value(field, "hunter2-secret")
    error = {"loc": ("body", field), "msg": "too short", "type": "string_too_short", "input": "hunter2-secret"}
    detail = safe_validation_errors([error])
    assert "hunter2-secret" not in str(detail)


def test_the_database_key_and_journals_are_created_owner_only(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    settings = Settings(_env_file=None, data_dir=data_dir, start_worker=False)  # type: ignore[call-arg]
    with TestClient(create_app(settings)) as client:
        assert client.get("/api/v1/health").status_code == 200
    assert mode(data_dir) == 0o700
    assert mode(data_dir / "ssp-rehab.sqlite3") == 0o600
    assert mode(data_dir / "secret_key") == 0o600
    for path in data_dir.rglob("*"):
        others = mode(path) & 0o077
        assert others == 0, f"{path} is open to others: {oct(mode(path))}"


def test_existing_files_open_to_others_are_tightened_at_start_and_logged(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    data_dir = tmp_path / "data"
    settings = Settings(_env_file=None, data_dir=data_dir, start_worker=False)  # type: ignore[call-arg]
    with TestClient(create_app(settings)):
        pass
    for path in [data_dir, *data_dir.rglob("*")]:
        os.chmod(path, 0o755 if path.is_dir() else 0o644)
    caplog.set_level(logging.WARNING)
    with TestClient(create_app(settings)):
        pass
    assert mode(data_dir / "ssp-rehab.sqlite3") == 0o600 and mode(data_dir / "secret_key") == 0o600
    assert mode(data_dir) == 0o700
    assert "ssp-rehab.sqlite3" in caplog.text and "0o644" in caplog.text and "0o600" in caplog.text
