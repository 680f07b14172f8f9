"""Login throttling that cannot be turned against a clinician (issue 20, defect 17): the address that
guesses backs off (X-Forwarded-For believed only from configured proxies); an account's failures from
anywhere only slow the next attempts on it by a bounded delay, so the right password still gets in from
another address; an admin can lift both."""

from __future__ import annotations

from typing import Any

import httpx
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from typer.testing import CliRunner

from server.app import create_app
from server.cli.main import app as cli
from server.db import Database
from server.settings import Settings
from tests.server.conftest import ADMIN_PASSWORD, THERAPIST_PASSWORD, Seed

ATTACKER = ("203.0.113.9", 5000)
CLINICIAN = ("10.0.0.20", 5000)


def login(client: TestClient, username: str, password: str, **kwargs: Any) -> httpx.Response:
    return client.post("/api/v1/auth/login", json={"username": username, "password": password}, **kwargs)


@pytest.fixture
def app(settings: Settings, database: Database) -> FastAPI:
    strict = settings.model_copy(update={"login_max_failures": 5, "login_window_s": 300.0})
    application = create_app(strict, database=database, worker=None)
    application.state.login_delays = delays = []

    async def recorded(seconds: float) -> None:  # the delay is taken, not waited for, in these tests
        delays.append(seconds)

    application.state.auth.throttle.sleep = recorded
    return application


def test_a_spoofed_forwarded_address_cannot_lock_a_clinician_out(app: FastAPI, seed: Seed) -> None:
    with TestClient(app, client=ATTACKER) as attacker, TestClient(app, client=CLINICIAN) as clinician:
        spoofed = {"X-Forwarded-For": CLINICIAN[0]}  # no proxy is configured: the header counts for nothing
        statuses = [login(attacker, "therapist", "guess", headers=spoofed).status_code for _ in range(7)]
        assert statuses == [401] * 5 + [429] * 2  # the address that guesses backs off
        response = login(clinician, "therapist", THERAPIST_PASSWORD)
        assert response.status_code == 200, response.text


def test_failures_spread_over_accounts_and_addresses_never_lock_the_admin_out(app: FastAPI, seed: Seed) -> None:
    """Four addresses, each under its own limit, guess at the admin, a therapist and unknown names: the
    admin's account is slowed (a delay before each check), never refused."""
    names = ("admin", "therapist", "nobody", "admin")
    with TestClient(app, client=CLINICIAN) as admin_desk:
        for octet in range(1, 5):
            attacker = TestClient(app, client=(f"198.51.100.{octet}", 5000))
            assert [login(attacker, name, "guess").status_code for name in names] == [401] * 4
        app.state.login_delays.clear()
        response = login(admin_desk, "admin", ADMIN_PASSWORD)
        assert response.status_code == 200, response.text
        assert app.state.login_delays and 0 < app.state.login_delays[-1] <= app.state.settings.login_delay_max_s
        app.state.login_delays.clear()
        assert login(admin_desk, "admin", "guess").status_code == 401
        assert app.state.login_delays == []  # the success cleared the account's record


def test_an_accounts_delay_grows_with_its_failures_and_is_bounded(app: FastAPI, seed: Seed) -> None:
    delays = app.state.login_delays
    for octet in range(1, 9):
        login(TestClient(app, client=(f"198.51.100.{octet}", 5000)), "therapist", "guess")
    assert delays == sorted(delays) and delays[0] > 0 and len(delays) == 3  # the 6th, 7th and 8th attempts
    for octet in range(9, 40):
        assert login(TestClient(app, client=(f"198.51.100.{octet}", 5000)), "therapist", "guess").status_code == 401
    assert max(delays) == app.state.settings.login_delay_max_s


def test_an_admin_unlocks_an_address_and_an_account(app: FastAPI, seed: Seed) -> None:
    with TestClient(app, client=ATTACKER) as locked_out, TestClient(app, client=CLINICIAN) as admin_desk:
        assert [login(locked_out, "therapist", "guess").status_code for _ in range(6)] == [401] * 5 + [429]
        refused = admin_desk.post("/api/v1/auth/unlock", json={"address": ATTACKER[0]}, headers=seed.headers())
        assert refused.status_code == 403  # admins only
        unlocked = admin_desk.post(
            "/api/v1/auth/unlock", json={"address": ATTACKER[0], "username": "therapist"}, headers=seed.headers("admin")
        )
        assert unlocked.status_code == 200, unlocked.text
        app.state.login_delays.clear()
        assert login(locked_out, "therapist", THERAPIST_PASSWORD).status_code == 200
        assert app.state.login_delays == []
        assert admin_desk.post("/api/v1/auth/unlock", json={}, headers=seed.headers("admin")).status_code == 422


def test_the_unlock_command(settings: Settings, tmp_path: Any) -> None:
    data_dir = tmp_path / "data"
    runner = CliRunner()
    created = runner.invoke(cli, ["create-user", "--username", "chief", "--password", "chief-password",
                                  "--role", "admin", "--data-dir", str(data_dir)])  # fmt: skip
    assert created.exit_code == 0, created.output
    local = Settings(_env_file=None, data_dir=data_dir, start_worker=False, login_max_failures=2)  # type: ignore[call-arg]
    with TestClient(create_app(local), client=ATTACKER) as attacker:
        assert [login(attacker, "chief", "guess").status_code for _ in range(3)] == [401, 401, 429]
        result = runner.invoke(cli, ["unlock-login", "--address", ATTACKER[0], "--data-dir", str(data_dir)])
        assert result.exit_code == 0, result.output
        assert ATTACKER[0] in result.output
        assert login(attacker, "chief", "chief-password").status_code == 200
    missing = runner.invoke(cli, ["unlock-login", "--data-dir", str(data_dir)])
    assert missing.exit_code != 0
