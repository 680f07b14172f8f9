"""Web security (issue 12 §5, defects 7–11; issue 15 §3): CSRF and Origin checks, security headers, login
throttling in the database (per account and per address, with backoff, atomic, across processes), trusted
proxies, no secrets in logs or 422s, a request-body limit, lone surrogates and out-of-range dates, and a
read-only database."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from fastapi.testclient import TestClient
from sqlalchemy import Engine

from server.app import create_app
from server.db import Database, DatabaseReadOnlyError, create_database_engine, upgrade_database
from server.security import shown_value
from server.settings import Settings
from tests.server.conftest import (
    ADMIN_PASSWORD,
    BACKENDS,
    TEST_SECRET,
    THERAPIST_PASSWORD,
    FakeWorker,
    Seed,
    _seed_accounts,
    booked_session,
    scratch_database,
)

REPOSITORY = Path(__file__).resolve().parents[2]
SERVED_ORIGIN = "http://testserver"  # TestClient's base URL
EVIL_ORIGIN = "http://evil.example"
CSRF_HEADERS = {"X-Requested-With": "ssp-rehab"}
COOKIE = "ssp_rehab_session"


def login(client: TestClient | httpx.Client, username: str, password: str, **kwargs: Any) -> httpx.Response:
    return client.post("/api/v1/auth/login", json={"username": username, "password": password}, **kwargs)


# --- defect 7: CSRF -----------------------------------------------------------------------------------

STATE_CHANGING = [
    "/api/v1/sessions/{id}/start",
    "/api/v1/sessions/{id}/pause",
    "/api/v1/sessions/{id}/resume",
    "/api/v1/sessions/{id}/stop",
    "/api/v1/estop",
    "/api/v1/robot/reset",
    "/api/v1/series/{id}/cancel",
    "/api/v1/auth/logout",
]


@pytest.mark.parametrize("path", STATE_CHANGING)
def test_a_cross_origin_cookie_request_is_refused_before_anything_happens(
    robot_client: TestClient, fake_worker: FakeWorker, seed: Seed, path: str
) -> None:
    booked = booked_session(robot_client, seed.headers())
    robot_client.cookies.set(COOKIE, seed.therapist_token)
    # Even with the console's own header: the Origin names another site.
    response = robot_client.post(path.format(id=booked.session_id), headers={"Origin": EVIL_ORIGIN, **CSRF_HEADERS})
    assert response.status_code == 403, (path, response.status_code, response.text)
    assert "evil.example" in response.json()["detail"]
    assert fake_worker.command_names() == []
    # The login was not ended by the refused logout.
    assert robot_client.get("/api/v1/auth/me").status_code == 200


def test_the_check_runs_before_any_lookup(robot_client: TestClient, seed: Seed) -> None:
    robot_client.cookies.set(COOKIE, seed.therapist_token)
    # A session that does not exist: a lookup would answer 404; the Origin check answers first.
    response = robot_client.post("/api/v1/sessions/999999/start", headers={"Origin": EVIL_ORIGIN})
    assert response.status_code == 403
    robot_client.cookies.set(COOKIE, "not-even-a-token")
    assert robot_client.post("/api/v1/auth/logout", headers={"Origin": EVIL_ORIGIN}).status_code == 403


def test_a_cookie_request_needs_the_console_header_even_without_an_origin(
    robot_client: TestClient, fake_worker: FakeWorker, seed: Seed
) -> None:
    booked = booked_session(robot_client, seed.headers())
    robot_client.cookies.set(COOKIE, seed.therapist_token)
    bare = robot_client.post(f"/api/v1/sessions/{booked.session_id}/start")
    assert bare.status_code == 403 and "X-Requested-With" in bare.json()["detail"]
    same_origin = robot_client.post(f"/api/v1/sessions/{booked.session_id}/start", headers={"Origin": SERVED_ORIGIN})
    assert same_origin.status_code == 403
    assert fake_worker.command_names() == []
    accepted = robot_client.post(
        f"/api/v1/sessions/{booked.session_id}/start", headers={"Origin": SERVED_ORIGIN, **CSRF_HEADERS}
    )
    assert accepted.status_code == 200, accepted.text
    assert "start_motion" in fake_worker.command_names()


def test_bearer_clients_are_unaffected(robot_client: TestClient, fake_worker: FakeWorker, seed: Seed) -> None:
    booked = booked_session(robot_client, seed.headers())
    response = robot_client.post(
        f"/api/v1/sessions/{booked.session_id}/start", headers={**seed.headers(), "Origin": EVIL_ORIGIN}
    )
    assert response.status_code == 200, response.text


def test_a_same_origin_emergency_stop_is_never_refused_by_the_csrf_check(
    robot_client: TestClient, fake_worker: FakeWorker, seed: Seed
) -> None:
    # The page's stop button must work with an expired or missing login and without the console header.
    robot_client.cookies.set(COOKIE, "an-expired-or-garbled-token")
    for headers in ({"Origin": SERVED_ORIGIN}, {}):
        assert robot_client.post("/api/v1/estop", headers=headers).status_code != 403
    robot_client.cookies.set(COOKIE, seed.therapist_token)
    assert robot_client.post("/api/v1/estop", headers={"Origin": SERVED_ORIGIN}).status_code == 200
    assert fake_worker.estopped.is_set()


def test_configured_origins_are_allowed(settings: Settings, database: Database, seed: Seed) -> None:
    other = settings.model_copy(update={"allowed_origins": ["https://console.clinic.example"]})
    with TestClient(create_app(other, database=database, worker=None)) as client:
        client.cookies.set(COOKIE, seed.therapist_token)
        headers = {"Origin": "https://console.clinic.example", **CSRF_HEADERS}
        assert client.post("/api/v1/auth/logout", headers=headers).status_code == 204


def test_a_cross_origin_websocket_is_refused(robot_client: TestClient, seed: Seed) -> None:
    """The telemetry socket authenticates with the cookie: another site must not watch a patient's session."""
    from starlette.websockets import WebSocketDisconnect

    booked = booked_session(robot_client, seed.headers())
    robot_client.cookies.set(COOKIE, seed.therapist_token)
    path = f"/api/v1/sessions/{booked.session_id}/telemetry"
    with robot_client.websocket_connect(path, headers={"Origin": SERVED_ORIGIN}):
        pass  # the console's own page is accepted
    with (
        pytest.raises(WebSocketDisconnect) as refused,
        robot_client.websocket_connect(path, headers={"Origin": EVIL_ORIGIN}),
    ):
        pass
    assert refused.value.code == 1008


def test_security_headers_on_every_response(client: TestClient, settings: Settings) -> None:
    for path in ("/", "/api/v1/health", "/api/v1/no-such-route", "/openapi.json", "/api/v1/auth/me"):
        headers = client.get(path).headers
        assert headers["x-content-type-options"] == "nosniff", path
        assert headers["x-frame-options"] == "SAMEORIGIN", path
        assert headers["referrer-policy"] == "no-referrer", path
        policy = headers["content-security-policy"]
        assert "frame-ancestors 'self'" in policy and "object-src 'none'" in policy, path
        assert "'unsafe-inline'" not in policy and "'unsafe-eval'" not in policy, path
    app_policy = client.get("/").headers["content-security-policy"]
    # The embedded 3D view is relayed by the console itself (server/viz/proxy.py): nothing else may be framed.
    assert "frame-src 'self';" in app_policy
    # Swagger UI runs an inline start-up script; its page alone allows that.
    docs = client.get("/docs")
    assert docs.status_code == 200
    assert "script-src 'self' 'unsafe-inline'" in docs.headers["content-security-policy"]
    client.cookies.set(COOKIE, "x")
    refused = client.post("/api/v1/auth/logout", headers={"Origin": EVIL_ORIGIN})
    assert refused.status_code == 403 and refused.headers["x-content-type-options"] == "nosniff"


def test_even_a_crash_answers_with_the_security_headers(settings: Settings, database: Database) -> None:
    app = create_app(settings, database=database, worker=None)

    def crash() -> None:
        raise RuntimeError("a bug")

    app.add_api_route("/api/v1/test-crash", crash)
    app.router.routes.insert(0, app.router.routes.pop())  # before the web app's catch-all mount at /
    with TestClient(app, raise_server_exceptions=False) as client:
        response = client.get("/api/v1/test-crash")
    assert response.status_code == 500
    assert response.headers["x-content-type-options"] == "nosniff" and "content-security-policy" in response.headers


def test_a_login_posted_from_another_site_is_refused(client: TestClient, seed: Seed) -> None:
    assert login(client, "admin", ADMIN_PASSWORD, headers={"Origin": EVIL_ORIGIN}).status_code == 403
    assert login(client, "admin", ADMIN_PASSWORD, headers={"Origin": SERVED_ORIGIN}).status_code == 200


# --- defect 8: throttling -----------------------------------------------------------------------------


def strict_settings(settings: Settings, **extra: Any) -> Settings:
    return settings.model_copy(update={"login_max_failures": 5, "login_window_s": 300.0, **extra})


def test_failures_for_an_unknown_user_never_lock_out_a_real_account(
    settings: Settings, database: Database, seed: Seed
) -> None:
    app = create_app(strict_settings(settings), database=database, worker=None)
    with TestClient(app, client=("10.0.0.1", 5000)) as client, TestClient(app, client=("10.0.0.2", 5000)) as other:
        # The address that guesses backs off (issue 20: per-address first), whatever names it tries ...
        assert [login(client, "nobody", "guess").status_code for _ in range(6)] == [401] * 5 + [429]
        # ... and the account is untouched: no delay, no refusal from anywhere else.
        assert login(other, "admin", ADMIN_PASSWORD).status_code == 200


def test_the_address_is_throttled_across_real_accounts_and_the_account_across_addresses(
    settings: Settings, database: Database, seed: Seed
) -> None:
    app = create_app(strict_settings(settings), database=database, worker=None)
    with TestClient(app, client=("10.0.0.1", 5000)) as first, TestClient(app, client=("10.0.0.2", 5000)) as second:
        statuses = [login(first, name, "guess").status_code for name in ("admin", "therapist") * 3]
        assert statuses == [401] * 5 + [429]
        assert login(first, "admin", ADMIN_PASSWORD).status_code == 429  # the address is locked out
        locked = login(first, "therapist", THERAPIST_PASSWORD)
        assert locked.status_code == 429 and int(locked.headers["Retry-After"]) > 0
        assert login(second, "admin", ADMIN_PASSWORD).status_code == 200  # three failures on admin: not locked
        # An account is never locked (issue 20, defect 17): its failures from anywhere delay the next attempts.
        app.state.auth.throttle.sleep = asyncio.sleep  # real delays: 1 s after the account's fifth failure
        assert [login(second, "therapist", "guess").status_code for _ in range(3)] == [401, 401, 401]
        started = time.monotonic()
        assert login(second, "therapist", THERAPIST_PASSWORD).status_code == 200
        assert time.monotonic() - started >= 1.0


def test_lockouts_back_off(settings: Settings, database: Database, seed: Seed) -> None:
    app = create_app(strict_settings(settings), database=database, worker=None)
    now = [1_000_000.0]
    app.state.auth.throttle.clock = lambda: now[0]

    async def no_wait(_seconds: float) -> None:  # the account's delays (test_login_lockout) are not timed here
        return None

    app.state.auth.throttle.sleep = no_wait
    with TestClient(app) as client:
        assert [login(client, "therapist", "guess").status_code for _ in range(6)] == [401] * 5 + [429]
        first_wait = int(login(client, "therapist", "guess").headers["Retry-After"])
        assert 0 < first_wait <= 300
        now[0] += 301
        assert [login(client, "therapist", "guess").status_code for _ in range(6)] == [401] * 5 + [429]
        second_wait = int(login(client, "therapist", "guess").headers["Retry-After"])
        assert second_wait > 2 * first_wait  # a second lockout lasts longer
        now[0] += second_wait + 1
        assert login(client, "therapist", THERAPIST_PASSWORD).status_code == 200
        assert login(client, "therapist", "guess").status_code == 401  # a success clears the account's record


def test_forwarded_addresses_count_only_from_configured_proxies(
    settings: Settings, database: Database, seed: Seed
) -> None:
    proxied = strict_settings(settings, trusted_proxies=["10.1.0.0/16"])
    app = create_app(proxied, database=database, worker=None)
    with TestClient(app, client=("10.1.0.5", 5000)) as via_proxy, TestClient(app, client=("10.9.9.9", 5000)) as direct:
        client_a = {"X-Forwarded-For": "198.51.100.1, 10.7.0.1"}  # the proxy appended the address it saw
        assert [
            login(via_proxy, name, "guess", headers=client_a).status_code for name in ("admin", "therapist") * 3
        ] == [401] * 5 + [429]
        # Another address behind the proxy is another client.
        assert login(via_proxy, "therapist", "guess", headers={"X-Forwarded-For": "10.7.0.2"}).status_code == 401
        # From anyone else the header is ignored: the sender's own address counts, whatever it claims.
        for name in ("clinician1", "clinician2", "clinician3"):
            created = direct.post(
                "/api/v1/users",
                json={"username": name, "password": "password-123", "role": "therapist"},
                headers=seed.headers("admin"),
            )
            assert created.status_code == 201, created.text
        claimed = [("10.7.0.1", "clinician1")] + [(f"10.8.0.{n}", f"clinician{n % 3 + 1}") for n in range(1, 6)]
        statuses = [
            login(direct, name, "guess", headers={"X-Forwarded-For": address}).status_code for address, name in claimed
        ]
        assert statuses == [401] * 5 + [429]  # no account has more than two failures: the address is locked


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def wait_for_health(base_url: str, process: subprocess.Popen[bytes] | None = None, timeout_s: float = 120) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if process is not None and process.poll() is not None:
            raise AssertionError(f"the service exited with {process.returncode}")
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(f"{base_url}/api/v1/health", timeout=2).status_code == 200:
                return
        time.sleep(0.2)
    raise AssertionError("the service did not answer")


def serve_environment(data_dir: Path) -> dict[str, str]:
    return {
        **os.environ,
        "PYTHONPATH": str(REPOSITORY),
        "SSP_REHAB_DATA_DIR": str(data_dir),
        "SSP_REHAB_SECRET_KEY": TEST_SECRET,
        "SSP_REHAB_VIZ_ENABLED": "false",
        "SSP_REHAB_LOGIN_MAX_FAILURES": "5",
    }


def serve_command(port: int, data_dir: Path) -> list[str]:
    return [
        sys.executable,
        "-m",
        "server.cli.main",
        "serve",
        "--no-robot",
        "--port",
        str(port),
        "--data-dir",
        str(data_dir),
    ]


def test_the_served_console_ignores_forwarded_for_from_loopback(tmp_path: Path) -> None:
    """`ssp-rehab serve` itself: uvicorn trusted X-Forwarded-For from loopback (12 spoofed addresses, 12 guesses)."""
    environment = serve_environment(tmp_path)
    names = [f"clinician{n}" for n in range(3)]
    for name in names:
        subprocess.run(
            [sys.executable, "-m", "server.cli.main", "create-user", "--username", name, "--password", "password-123",
             "--role", "therapist", "--data-dir", str(tmp_path)],
            env=environment, check=True, capture_output=True,
        )  # fmt: skip
    port = free_port()
    process = subprocess.Popen(
        serve_command(port, tmp_path), env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        base_url = f"http://127.0.0.1:{port}"
        wait_for_health(base_url, process)
        with httpx.Client(base_url=base_url, timeout=30) as http:
            # Two guesses per account (below its limit), each from a "new" address: six failures from one sender.
            statuses = [
                login(http, names[n % 3], "guess", headers={"X-Forwarded-For": f"203.0.113.{n}"}).status_code
                for n in range(6)
            ]
        assert statuses == [401] * 5 + [429]
    finally:
        process.terminate()
        process.wait(30)


@contextlib.contextmanager
def live_server(app: Any) -> Iterator[str]:
    """The app under a real uvicorn in a thread (its own protocols and loggers), on a free loopback port."""
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_config=None, log_level="info"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    try:
        wait_for_health(f"http://127.0.0.1:{port}")
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(30)


@pytest.fixture(params=BACKENDS)
def shared_database(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[str, Seed]]:
    """A migrated database with the seeded accounts, shared by several app instances (own engines)."""
    scratch = scratch_database(request.param, tmp_path)
    try:
        upgrade_database(scratch.engine)
        yield scratch.url, _seed_accounts(scratch.engine, request.param)
    finally:
        scratch.drop()


@contextlib.contextmanager
def app_instance(url: str, settings: Settings) -> Iterator[tuple[TestClient, Engine]]:
    engine = create_database_engine(url)
    try:
        with TestClient(create_app(settings, database=Database(engine), worker=None)) as client:
            yield client, engine
    finally:
        engine.dispose()


def test_thirty_parallel_guesses_get_at_most_five_checked(
    shared_database: tuple[str, Seed], settings: Settings
) -> None:
    url, _seed = shared_database
    engine = create_database_engine(url)
    app = create_app(strict_settings(settings), database=Database(engine), worker=None)
    try:
        with live_server(app) as base_url, httpx.Client(base_url=base_url, timeout=120) as http:
            barrier = threading.Barrier(30)

            def guess(n: int) -> int:
                barrier.wait()
                return login(http, "therapist", f"guess-{n}").status_code

            with ThreadPoolExecutor(30) as pool:
                statuses = list(pool.map(guess, range(30)))
    finally:
        engine.dispose()
    assert statuses.count(401) <= 5 and statuses.count(401) + statuses.count(429) == 30, statuses


def test_two_consoles_share_revocation_and_throttling(shared_database: tuple[str, Seed], settings: Settings) -> None:
    """Issue 15 §3: two app instances (own engines, as two processes would have) on one database."""
    url, _seed = shared_database
    with (
        app_instance(url, strict_settings(settings)) as (first, _),
        app_instance(url, strict_settings(settings)) as (
            second,
            _,
        ),
    ):
        token = login(first, "admin", ADMIN_PASSWORD).json()["access_token"]
        bearer = {"Authorization": f"Bearer {token}"}
        assert second.get("/api/v1/auth/me", headers=bearer).status_code == 200
        assert first.post("/api/v1/auth/logout", headers=bearer).status_code == 204
        assert second.get("/api/v1/auth/me", headers=bearer).status_code == 401
        statuses = [login(client, "therapist", "guess").status_code for client in (first, second) * 3]
        assert statuses == [401] * 5 + [429]
        assert login(first, "therapist", THERAPIST_PASSWORD).status_code == 429


# --- defect 9: secrets in logs and answers, body limit ----------------------------------------------------


def test_the_websocket_token_never_reaches_the_log(
    shared_database: tuple[str, Seed], settings: Settings, caplog: pytest.LogCaptureFixture
) -> None:
    import websockets.sync.client

    url, seed = shared_database
    caplog.set_level(logging.DEBUG)
    engine = create_database_engine(url)
    try:
        with live_server(create_app(settings, database=Database(engine), worker=None)) as base_url:
            ws_url = base_url.replace("http", "ws") + f"/api/v1/sessions/1/telemetry?token={seed.therapist_token}"
            with contextlib.suppress(Exception), websockets.sync.client.connect(ws_url, open_timeout=10) as socket_:
                socket_.recv(timeout=5)
            httpx.get(f"{base_url}/api/v1/auth/me?token={seed.therapist_token}")
            httpx.get(f"{base_url}/api/v1/auth/me", headers={"Authorization": f"Bearer {seed.admin_token}"})
    finally:
        engine.dispose()
    # The test's own clients (httpx, the websockets client) log their requests; only the service's records count.
    service_records = [r for r in caplog.records if not r.name.startswith(("httpx", "httpcore", "websockets.client"))]
    logged = "\n".join(record.getMessage() for record in service_records)
    assert "WebSocket" in logged  # uvicorn did log the connection
    assert seed.therapist_token not in logged and seed.admin_token not in logged
    signature = seed.therapist_token.rsplit(".", 1)[-1]
    assert signature not in logged


def test_a_422_never_echoes_a_password_or_a_long_input(client: TestClient, seed: Seed) -> None:
    password = "my-secret-password-" + "x" * 300  # too long: refused by the schema
    response = login(client, "admin", password)
    assert response.status_code == 422
    assert "my-secret-password" not in response.text
    assert response.json()["detail"][0]["loc"] == ["body", "password"]
    long_name = "Q" * 5000
    refused = client.post("/api/v1/patients", json={"name": long_name}, headers=seed.headers())
    assert refused.status_code == 422
    assert "Q" * 200 not in refused.text and len(refused.content) < 4000


def test_domain_refusals_cut_long_values_and_never_show_secrets() -> None:
    assert shown_value("segments[0].cue.rows", "1,2\n" * 10_000).endswith(" characters)")
    assert len(shown_value("segments[0].cue.rows", "1,2\n" * 10_000)) < 120
    assert shown_value("duration_s", 1e9) == "1000000000.0"
    assert shown_value("account.password", "hunter2-hunter2") == "(not shown)"


def test_bodies_over_the_limit_get_413_before_parsing(settings: Settings, database: Database, seed: Seed) -> None:
    small = settings.model_copy(update={"max_request_body_bytes": 10_000})
    with TestClient(create_app(small, database=database, worker=None)) as client:
        oversized = b"{" + b" " * 20_000  # not even JSON: a parser would answer 422
        response = client.post(
            "/api/v1/patients", content=oversized, headers={**seed.headers(), "Content-Type": "application/json"}
        )
        assert response.status_code == 413
        assert "10000" in response.json()["detail"]

        def chunks() -> Iterator[bytes]:  # no Content-Length: counted while it arrives
            for _ in range(30):
                yield b" " * 1000

        streamed = client.post("/api/v1/auth/login", content=chunks(), headers={"Content-Type": "application/json"})
        assert streamed.status_code == 413
        assert login(client, "admin", ADMIN_PASSWORD).status_code == 200  # small bodies still pass


# --- defect 10: surrogates and dates ---------------------------------------------------------------------


@pytest.mark.parametrize(
    ("path", "body", "authenticated"),
    [
        ("/api/v1/auth/login", '{"username": "\\ud800", "password": "x"}', False),
        ("/api/v1/auth/login", '{"username": "admin", "password": "\\udfff\\ud800"}', False),
        ("/api/v1/patients", '{"identifier": "MRN-1", "name": "A \\ud800 B"}', True),
        ("/api/v1/patients", '{"\\ud800": 1}', True),
    ],
)
def test_a_lone_surrogate_gives_422(client: TestClient, seed: Seed, path: str, body: str, authenticated: bool) -> None:
    headers = {"Content-Type": "application/json", **(seed.headers() if authenticated else {})}
    response = client.post(path, content=body.encode(), headers=headers)
    assert response.status_code == 422, response.text
    assert "surrogate" in response.text


def test_a_surrogate_pair_is_ordinary_text(client: TestClient, seed: Seed) -> None:
    response = client.post(
        "/api/v1/auth/login",
        content=b'{"username": "\\ud83d\\ude00", "password": "x"}',
        headers={"Content-Type": "application/json"},
    )
    assert response.status_code == 401


@pytest.mark.parametrize(
    "params",
    [{"from_date": "2026-01-01", "to_date": "9999-12-31"}, {"from_date": "9999-12-31", "to_date": "9999-12-31"}],
)
def test_out_of_range_export_dates_give_422(client: TestClient, seed: Seed, params: dict[str, str]) -> None:
    response = client.get("/api/v1/exports/bulk", params=params, headers=seed.headers("admin"))
    assert response.status_code == 422, response.text


# --- defect 11: a read-only database ----------------------------------------------------------------------


@contextlib.contextmanager
def immutable(path: Path) -> Iterator[None]:
    """Read-only even for root: the immutable attribute (chmod does not stop root)."""
    if subprocess.run(["chattr", "+i", str(path)], capture_output=True).returncode != 0:
        pytest.skip("chattr +i is not permitted here")
    try:
        yield
    finally:
        subprocess.run(["chattr", "-i", str(path)], check=True)


def test_a_read_only_database_file_stops_the_start_with_a_clear_message(tmp_path: Path) -> None:
    database_file = tmp_path / "ssp-rehab.sqlite3"
    engine = create_database_engine(f"sqlite:///{database_file}")
    upgrade_database(engine)
    engine.dispose()
    for leftover in tmp_path.glob("ssp-rehab.sqlite3-*"):
        leftover.unlink()
    with immutable(database_file):
        port = free_port()
        result = subprocess.run(
            serve_command(port, tmp_path), env=serve_environment(tmp_path), capture_output=True, text=True, timeout=60
        )
    assert result.returncode != 0
    assert f"database file {database_file} is read-only" in result.stdout + result.stderr


def test_a_login_on_a_read_only_database_is_a_clear_503(tmp_path: Path, settings: Settings) -> None:
    database_file = tmp_path / "ro.sqlite3"
    writable = create_database_engine(f"sqlite:///{database_file}")
    upgrade_database(writable)
    _seed_accounts(writable, "sqlite")
    writable.dispose()
    read_only = create_database_engine(f"sqlite:///file:{database_file}?mode=ro&uri=true")
    try:
        assert_login_is_refused_as_read_only(settings, read_only)
    finally:
        read_only.dispose()


def assert_login_is_refused_as_read_only(settings: Settings, read_only: Engine) -> None:
    """The login answers 503 naming the cause, and from then on the health check reports it."""
    with TestClient(create_app(settings, database=Database(read_only), worker=None)) as client:
        assert client.get("/api/v1/health").json()["database"] == {"reachable": True, "writable": True, "reason": None}
        response = login(client, "admin", ADMIN_PASSWORD)
        assert response.status_code == 503, response.text
        assert "is read-only: nothing was written" in response.json()["detail"]
        health = client.get("/api/v1/health").json()
        assert health["status"] == "degraded" and health["database"]["writable"] is False
        assert "is read-only" in health["database"]["reason"]


@pytest.mark.postgres
def test_a_read_only_postgresql_database_is_refused_at_start_and_answers_503(
    tmp_path: Path, settings: Settings
) -> None:
    scratch = scratch_database("postgresql", tmp_path)
    try:
        upgrade_database(scratch.engine)
        _seed_accounts(scratch.engine, "postgresql")
        schema = scratch.url.rsplit("%3D", 1)[-1]
        read_only = create_database_engine(
            scratch.url.split("?", 1)[0],
            connect_args={"options": f"-csearch_path={schema} -cdefault_transaction_read_only=on"},
        )
        try:
            with pytest.raises(DatabaseReadOnlyError, match="is read-only"):
                upgrade_database(read_only)
            assert_login_is_refused_as_read_only(settings, read_only)
        finally:
            read_only.dispose()
    finally:
        scratch.drop()


# --- OpenAPI ------------------------------------------------------------------------------------------------


def test_openapi_documents_401_403_and_413_where_they_apply(client: TestClient) -> None:
    paths = client.get("/openapi.json").json()["paths"]
    start = paths["/api/v1/sessions/{session_id}/start"]["post"]["responses"]
    assert {"401", "403"} <= start.keys() and "413" not in start  # no body
    create_patient_ = paths["/api/v1/patients"]["post"]["responses"]
    assert {"401", "403", "413", "422"} <= create_patient_.keys()
    assert "X-Requested-With" in create_patient_["403"]["description"]
    login_ = paths["/api/v1/auth/login"]["post"]["responses"]
    assert {"403", "413", "429"} <= login_.keys() and login_["401"]["description"] == "Wrong username or password"
    assert "401" not in paths["/api/v1/health"]["get"]["responses"]
