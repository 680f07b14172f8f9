"""Authentication and security: login (cookie + bearer), logout, throttling, cookie flags, CORS, role
checks, every route protected, no patient data in logs."""

from __future__ import annotations

import logging
import os

import pytest
from fastapi.routing import iter_route_contexts
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from server.app import RedactQueryStrings, create_app
from server.db import Database
from server.settings import Settings
from tests.server.conftest import ADMIN_PASSWORD, PATIENT, THERAPIST_PASSWORD, Seed, create_patient

# Public: the calendar subscription link (its secret path is the credential; calendar apps cannot log in) and
# the emergency stop (the console page must stop motion logged in or not: issue 12, defect 12).
PUBLIC_ROUTES = {
    ("GET", "/api/v1/health"),
    ("POST", "/api/v1/auth/login"),
    ("GET", "/api/v1/calendar/{token}.ics"),
    ("POST", "/api/v1/estop"),
}
# Framework pages that carry no data: the OpenAPI document and its viewers.
DOCUMENTATION_PATHS = {"/openapi.json", "/docs", "/docs/oauth2-redirect", "/redoc"}


def login(client: TestClient, username: str, password: str) -> object:
    return client.post("/api/v1/auth/login", json={"username": username, "password": password})


def test_health_is_public_and_reports_no_robot(client: TestClient) -> None:
    response = client.get("/api/v1/health")
    assert response.status_code == 200
    assert response.json() == {
        "status": "ok",
        "recording": {"ok": True, "reason": None},
        "reasons": [],
        "robot_connected": False,
        "robot": {"state": "absent", "reason": "this console runs without a robot"},
        "database": {"reachable": True, "writable": True, "reason": None},
        "web_pid": os.getpid(),  # the process that answered (here the test's own, in-process app)
        "clinic_timezone": client.app.state.settings.timezone,  # type: ignore[attr-defined]
        "estop": {"url": None, "fallback": "/api/v1/estop"},  # no robot, no stop listener: the web route
        "realtime": None,  # no robot daemon, no worker to schedule
    }


def test_login_answers_with_a_strict_http_only_cookie_and_a_bearer_token(client: TestClient, seed: Seed) -> None:
    response = login(client, "therapist", THERAPIST_PASSWORD)
    assert response.status_code == 200
    body = response.json()
    assert body["token_type"] == "bearer" and body["user"]["role"] == "therapist"
    cookie = response.headers["set-cookie"]
    assert "HttpOnly" in cookie and "SameSite=strict" in cookie and "Path=/" in cookie
    assert "Secure" not in cookie  # off by default: the embedded default serves plain HTTP on loopback
    assert cookie.startswith(f"ssp_rehab_session={body['access_token']};")
    bearer = client.get("/api/v1/auth/me", headers={"Authorization": f"Bearer {body['access_token']}"})
    assert bearer.json()["username"] == "therapist"
    client.cookies.set("ssp_rehab_session", body["access_token"])
    assert client.get("/api/v1/auth/me").json()["username"] == "therapist"


def test_secure_cookie_flag_is_configurable(settings: Settings, database: Database, seed: Seed) -> None:
    secure = settings.model_copy(update={"cookie_secure": True})
    with TestClient(create_app(secure, database=database, worker=None)) as client:
        assert "Secure" in login(client, "admin", ADMIN_PASSWORD).headers["set-cookie"]


def test_wrong_password_and_unknown_user_get_the_same_401(client: TestClient, seed: Seed) -> None:
    wrong = login(client, "therapist", "not-the-password")
    unknown = login(client, "nobody", "not-the-password")
    assert wrong.status_code == unknown.status_code == 401
    assert wrong.json() == unknown.json()


def test_login_is_throttled_after_repeated_failures_even_with_the_right_password(
    settings: Settings, database: Database, seed: Seed
) -> None:
    strict = settings.model_copy(update={"login_max_failures": 3})
    with TestClient(create_app(strict, database=database, worker=None)) as client:
        assert [login(client, "therapist", "wrong-password").status_code for _ in range(3)] == [401] * 3
        locked = login(client, "therapist", THERAPIST_PASSWORD)
        assert locked.status_code == 429
        assert int(locked.headers["Retry-After"]) > 0
        # The back-off is the address's: the admin from another address may still log in.
        other = TestClient(client.app, client=("10.0.0.9", 5000))
        assert login(other, "admin", ADMIN_PASSWORD).status_code == 200


def test_logout_revokes_the_token(client: TestClient, seed: Seed) -> None:
    token = login(client, "admin", ADMIN_PASSWORD).json()["access_token"]
    headers = {"Authorization": f"Bearer {token}"}
    assert client.post("/api/v1/auth/logout", headers=headers).status_code == 204
    assert client.get("/api/v1/auth/me", headers=headers).status_code == 401


def test_a_tampered_token_is_refused(client: TestClient, seed: Seed) -> None:
    session_id, _user_id, expires, signature = seed.therapist_token.split(".")
    forged = f"{session_id}.{seed.admin_id}.{expires}.{signature}"  # claim to be the admin
    assert client.get("/api/v1/users", headers={"Authorization": f"Bearer {forged}"}).status_code == 401


def test_every_route_but_health_and_login_requires_authentication(client: TestClient) -> None:
    checked = 0
    for route in iter_route_contexts(client.app.routes):
        path = route.path
        if path in DOCUMENTATION_PATHS or not path.startswith("/api/"):
            continue
        concrete = _with_ids(path)
        if route.methods is None:  # the telemetry WebSocket
            with pytest.raises(WebSocketDisconnect) as refused, client.websocket_connect(concrete):
                pass
            assert refused.value.code == 1008
            checked += 1
            continue
        for method in route.methods - {"HEAD"}:
            response = client.request(method, concrete, json={})
            if (method, path) in PUBLIC_ROUTES:
                assert response.status_code != 401, (method, path)
            else:
                assert response.status_code == 401, (method, path, response.status_code)
                assert response.headers["WWW-Authenticate"] == "Bearer"
            checked += 1
    assert checked >= 35  # the enumeration really found the API


def _with_ids(path: str) -> str:
    import re

    return re.sub(r"\{[^}]+\}", "1", path)


def test_admin_routes_refuse_therapists(client: TestClient, seed: Seed) -> None:
    for path in ("/api/v1/users", "/api/v1/audit"):
        assert client.get(path, headers=seed.headers("therapist")).status_code == 403
        assert client.get(path, headers=seed.headers("admin")).status_code == 200


def test_cors_is_closed_by_default_and_opens_only_to_configured_origins(
    client: TestClient, settings: Settings, database: Database
) -> None:
    preflight = {"Origin": "https://evil.example", "Access-Control-Request-Method": "GET"}
    response = client.options("/api/v1/health", headers=preflight)
    assert "access-control-allow-origin" not in response.headers
    opened = settings.model_copy(update={"cors_origins": ["https://console.clinic.example"]})
    with TestClient(create_app(opened, database=database, worker=None)) as cors_client:
        allowed = {"Origin": "https://console.clinic.example", "Access-Control-Request-Method": "GET"}
        answer = cors_client.options("/api/v1/health", headers=allowed)
        assert answer.headers["access-control-allow-origin"] == "https://console.clinic.example"
        assert "access-control-allow-origin" not in cors_client.options("/api/v1/health", headers=preflight).headers


def test_no_patient_data_reaches_the_logs(client: TestClient, seed: Seed, caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    headers = seed.headers()
    patient_id = create_patient(client, headers)
    client.get("/api/v1/patients", params={"search": PATIENT["name"]}, headers=headers)
    client.get(f"/api/v1/patients/{patient_id}", headers=headers)
    client.post("/api/v1/patients", json=PATIENT, headers=headers)  # a 409: the error path logs too
    # The test's own HTTP client (httpx) logs its requests; only the service's records count.
    logged = "\n".join(r.getMessage() for r in caplog.records if not r.name.startswith("httpx"))
    for value in (PATIENT["name"], PATIENT["identifier"], "Testperson"):
        assert value not in logged


def test_access_log_filter_strips_query_strings() -> None:
    record = logging.LogRecord(
        "uvicorn.access",
        logging.INFO,
        __file__,
        1,
        '%s - "%s %s HTTP/%s" %d',
        ("127.0.0.1:5000", "GET", "/api/v1/patients?search=Greta%20Testperson", "1.1", 200),
        None,
    )
    assert RedactQueryStrings().filter(record)
    assert "Greta" not in record.getMessage() and "/api/v1/patients" in record.getMessage()
