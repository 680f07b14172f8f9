"""`/users` (admin only) and `ssp-rehab create-user`; the first start tells how to create the first admin."""

from __future__ import annotations

import logging
import shlex
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from server.app import create_app
from server.cli.main import app as cli
from server.settings import Settings
from tests.server.conftest import TEST_SECRET, Seed

NEW_USER = {"username": "jdoe", "password": "correct horse battery", "role": "therapist", "full_name": "J. Doe"}


def test_admin_creates_lists_and_updates_accounts(client: TestClient, seed: Seed) -> None:
    admin = seed.headers("admin")
    created = client.post("/api/v1/users", json=NEW_USER, headers=admin)
    assert created.status_code == 201
    user = created.json()
    assert "password" not in user and "password_hash" not in user
    assert user["username"] == "jdoe" in [u["username"] for u in client.get("/api/v1/users", headers=admin).json()]
    promoted = client.patch(f"/api/v1/users/{user['id']}", json={"role": "admin"}, headers=admin)
    assert promoted.json()["role"] == "admin"
    login = client.post("/api/v1/auth/login", json={"username": "JDOE", "password": NEW_USER["password"]})
    assert login.status_code == 200  # usernames are case-insensitive


def test_duplicate_usernames_bad_roles_and_short_passwords_are_refused(client: TestClient, seed: Seed) -> None:
    admin = seed.headers("admin")
    duplicate = client.post("/api/v1/users", json={**NEW_USER, "username": "Therapist"}, headers=admin)
    assert duplicate.status_code == 409 and duplicate.json()["field"] == "username"
    invalid = client.post("/api/v1/users", json={**NEW_USER, "role": "root", "password": "short"}, headers=admin)
    assert invalid.status_code == 422
    assert {("body", "role"), ("body", "password")} <= {tuple(e["loc"]) for e in invalid.json()["detail"]}
    assert client.get("/api/v1/users/424242", headers=admin).status_code == 404


def test_the_last_active_admin_cannot_be_demoted_or_deactivated(client: TestClient, seed: Seed) -> None:
    admin = seed.headers("admin")
    for change in ({"role": "therapist"}, {"is_active": False}):
        response = client.patch(f"/api/v1/users/{seed.admin_id}", json=change, headers=admin)
        assert response.status_code == 409


def test_deactivating_an_account_ends_its_login_sessions(client: TestClient, seed: Seed) -> None:
    assert client.get("/api/v1/auth/me", headers=seed.headers("therapist")).status_code == 200
    response = client.patch(
        f"/api/v1/users/{seed.therapist_id}", json={"is_active": False}, headers=seed.headers("admin")
    )
    assert response.status_code == 200
    assert client.get("/api/v1/auth/me", headers=seed.headers("therapist")).status_code == 401


def test_create_user_command_and_first_start_message(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    settings = Settings(_env_file=None, data_dir=tmp_path, secret_key=TEST_SECRET, start_worker=False)  # type: ignore[call-arg]
    caplog.set_level(logging.WARNING, logger="server.app")
    with TestClient(create_app(settings)) as client:  # upgrades the new database at start
        assert client.get("/api/v1/health").status_code == 200
    assert "ssp-rehab create-user" in caplog.text and "--role admin" in caplog.text

    runner = CliRunner()
    args = ["create-user", "--username", "chief", "--password", "chief-password", "--role", "admin"]
    result = runner.invoke(cli, [*args, "--data-dir", str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    assert '"role": "admin"' in result.output
    again = runner.invoke(cli, [*args, "--data-dir", str(tmp_path)])
    assert again.exit_code != 0 and "taken" in again.output
    bad_role = runner.invoke(
        cli,
        [
            "create-user",
            "--username",
            "x1y",
            "--password",
            "long-enough",
            "--role",
            "boss",
            "--data-dir",
            str(tmp_path),
        ],
    )
    assert bad_role.exit_code != 0 and "role" in bad_role.output

    caplog.clear()
    with TestClient(create_app(settings)) as client:
        login = client.post("/api/v1/auth/login", json={"username": "chief", "password": "chief-password"})
        assert login.status_code == 200 and login.json()["user"]["role"] == "admin"
    assert "create-user" not in caplog.text


def test_first_start_hint_is_a_copyable_command_that_prompts_for_the_password(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    data_dir = tmp_path / "data dir with spaces"
    settings = Settings(_env_file=None, data_dir=data_dir, secret_key=TEST_SECRET, start_worker=False)  # type: ignore[call-arg]
    caplog.set_level(logging.WARNING, logger="server.app")
    with TestClient(create_app(settings)):
        pass
    command_line = caplog.text.split("create the first admin", 1)[1].splitlines()[1].strip()
    assert "--password" not in command_line and "<password>" not in command_line  # never in the shell history
    words = shlex.split(command_line)
    executable = Path(words[0])
    assert executable.is_absolute() and executable.is_file(), f"{words[0]} is not this installation's CLI"
    arguments = words[words.index("create-user") :]
    assert arguments[arguments.index("--data-dir") + 1] == str(data_dir.resolve())
    # The command as printed asks for the password twice (hidden) and creates the admin.
    result = CliRunner().invoke(cli, arguments, input="first-admin-pass\nfirst-admin-pass\n")
    assert result.exit_code == 0, result.output
    assert "Password" in result.output
    with TestClient(create_app(settings)) as client:
        login = client.post("/api/v1/auth/login", json={"username": "admin", "password": "first-admin-pass"})
        assert login.status_code == 200 and login.json()["user"]["role"] == "admin"
