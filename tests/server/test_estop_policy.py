"""Defect 12 of issue 12: the console page can always stop motion, logged in or not; logging out during
motion is refused; every stop is audited truthfully (an unauthenticated or no-longer-valid credential is
never named as a user)."""

from __future__ import annotations

from fastapi.testclient import TestClient

from tests.server.conftest import THERAPIST_PASSWORD, FakeWorker, Seed, booked_session, wait_until


def robot_audit(client: TestClient, seed: Seed) -> list[dict]:
    entries = client.get("/api/v1/audit", params={"resource_type": "robot"}, headers=seed.headers("admin")).json()
    return [e for e in entries if e["details"].get("command") == "emergency_stop"]


def login(client: TestClient, username: str, password: str) -> dict[str, str]:
    response = client.post("/api/v1/auth/login", json={"username": username, "password": password})
    assert response.status_code == 200, response.text
    return {"Authorization": f"Bearer {response.json()['access_token']}"}


def test_defect_12_the_estop_works_logged_out_and_is_audited_as_unauthenticated(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    booked = booked_session(robot_client, seed.headers())
    assert robot_client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers()).status_code == 200
    response = robot_client.post("/api/v1/estop")  # no cookie, no token: the page after a logout
    assert response.status_code == 200, response.text
    assert fake_worker.estopped.is_set()
    entry = wait_until(lambda: robot_audit(robot_client, seed))[0]
    assert entry["user_id"] is None and entry["details"]["authenticated"] is False, entry


def test_defect_12_a_revoked_or_deactivated_credential_stops_but_is_not_named(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    created = robot_client.post(
        "/api/v1/users",
        json={"username": "leaver", "password": THERAPIST_PASSWORD, "role": "therapist"},
        headers=seed.headers("admin"),
    )
    assert created.status_code == 201, created.text
    leaver = login(robot_client, "leaver", THERAPIST_PASSWORD)
    patched = robot_client.patch(
        f"/api/v1/users/{created.json()['id']}", json={"is_active": False}, headers=seed.headers("admin")
    )
    assert patched.status_code == 200, patched.text
    logged_out = login(robot_client, "therapist", THERAPIST_PASSWORD)
    assert robot_client.post("/api/v1/auth/logout", headers=logged_out).status_code == 204
    for headers in (leaver, logged_out):
        fake_worker.estopped.clear()
        assert robot_client.post("/api/v1/estop", headers=headers).status_code == 200
        assert fake_worker.estopped.is_set()
    entries = wait_until(lambda: len(e := robot_audit(robot_client, seed)) >= 2 and e)
    for entry in entries[:2]:
        assert entry["user_id"] is None and entry["details"]["authenticated"] is False, entry
    assert robot_client.post("/api/v1/estop", headers=seed.headers()).status_code == 200
    named = wait_until(lambda: len(e := robot_audit(robot_client, seed)) >= 3 and e)[0]
    assert named["user_id"] == seed.therapist_id and named["details"]["authenticated"] is True, named


def test_defect_12_logout_during_motion_is_refused_with_the_reason(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    headers = login(robot_client, "therapist", THERAPIST_PASSWORD)
    booked = booked_session(robot_client, headers)
    assert robot_client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=headers).status_code == 200
    refused = robot_client.post("/api/v1/auth/logout", headers=headers)
    assert refused.status_code == 409, refused.text
    assert "motion" in refused.json()["detail"] and "emergency stop" in refused.json()["detail"]
    assert robot_client.post(f"/api/v1/sessions/{booked.session_id}/stop", headers=headers).status_code == 200
    assert robot_client.post("/api/v1/auth/logout", headers=headers).status_code == 204
