"""An open telemetry WebSocket ends with its login (issue 20, defect 16: 248 frames in the 10 s after
POST /auth/logout): logout, a revocation by another web process, and an account's deactivation each close
it with code 1008 and a reason that says which."""

from __future__ import annotations

import datetime as dt
import time
from collections.abc import Callable

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import update
from starlette.testclient import WebSocketTestSession
from starlette.websockets import WebSocketDisconnect

from server.auth.models import AuthSession
from server.db import Database
from tests.server.conftest import Seed, booked_session

CLOSE_BOUND_S = 10.0  # generous: the check runs every second; a loaded machine may be slow


def login(client: TestClient, username: str, password: str) -> dict[str, str]:
    response = client.post("/api/v1/auth/login", json={"username": username, "password": password})
    assert response.status_code == 200, response.text
    return {"Authorization": f"Bearer {response.json()['access_token']}"}


def new_therapist(client: TestClient, seed: Seed) -> tuple[int, dict[str, str]]:
    account = {"username": "watcher", "password": "watcher-password", "role": "therapist"}
    created = client.post("/api/v1/users", json=account, headers=seed.headers("admin"))
    assert created.status_code == 201, created.text
    return int(created.json()["id"]), login(client, "watcher", "watcher-password")


def frames_until_closed(socket: WebSocketTestSession, end_login: Callable[[], None]) -> tuple[int, float, int, str]:
    """Ends the login while frames flow; the frames after that, the seconds to the close, its code and reason."""
    socket.receive_text()
    end_login()
    ended = time.monotonic()
    frames = 0
    while time.monotonic() - ended < CLOSE_BOUND_S:
        try:
            socket.receive_text()
        except WebSocketDisconnect as closed:
            return frames, time.monotonic() - ended, closed.code, closed.reason
        frames += 1
    pytest.fail(f"the WebSocket was still open {CLOSE_BOUND_S} s after the login ended ({frames} frames)")


def test_logout_closes_the_telemetry_websocket(robot_client: TestClient, seed: Seed) -> None:
    _user_id, headers = new_therapist(robot_client, seed)
    booked = booked_session(robot_client, headers)
    with robot_client.websocket_connect(f"/api/v1/sessions/{booked.session_id}/telemetry", headers=headers) as socket:

        def logout() -> None:
            assert robot_client.post("/api/v1/auth/logout", headers=headers).status_code == 204

        _frames, _seconds, code, reason = frames_until_closed(socket, logout)
    assert (code, reason) == (1008, "logged out")


def test_deactivating_the_account_closes_its_websocket(robot_client: TestClient, seed: Seed) -> None:
    user_id, headers = new_therapist(robot_client, seed)
    booked = booked_session(robot_client, headers)
    with robot_client.websocket_connect(f"/api/v1/sessions/{booked.session_id}/telemetry", headers=headers) as socket:

        def deactivate() -> None:
            changed = robot_client.patch(f"/api/v1/users/{user_id}", json={"is_active": False},
                                         headers=seed.headers("admin"))  # fmt: skip
            assert changed.status_code == 200, changed.text

        _frames, _seconds, code, reason = frames_until_closed(socket, deactivate)
    assert (code, reason) == (1008, "account deactivated")


def test_a_revocation_by_another_web_process_closes_the_websocket(
    robot_client: TestClient, seed: Seed, database: Database
) -> None:
    """Another web process revoked the login: only the database says so."""
    user_id, headers = new_therapist(robot_client, seed)
    booked = booked_session(robot_client, headers)
    with robot_client.websocket_connect(f"/api/v1/sessions/{booked.session_id}/telemetry", headers=headers) as socket:

        def revoke_elsewhere() -> None:
            with database.session() as session:
                session.execute(update(AuthSession).where(AuthSession.user_id == user_id)
                                .values(revoked_at=dt.datetime.now(dt.UTC)))  # fmt: skip
                session.commit()

        _frames, _seconds, code, reason = frames_until_closed(socket, revoke_elsewhere)
    assert (code, reason) == (1008, "login session revoked")
