"""Fixtures for the console-service tests: migrated SQLite and PostgreSQL databases, each test inside a
transaction that is rolled back, seeded accounts with tokens, the app, and a fake real-time worker that
implements the agreed WorkerClient interface."""

from __future__ import annotations

import datetime as dt
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import Engine, create_engine, text

from benchmarks.fault_harness import EVENT_TIMEOUT_S, Console, wait_for
from server.app import create_app
from server.auth.models import AuthSession
from server.auth.security import TokenClaims, TokenSigner, hash_password, new_session_id
from server.db import Database, create_database_engine, upgrade_database
from server.realtime.supervisor import STOP_RAMP_RUNNING, TransitionRefused
from server.realtime.telemetry import TELEMETRY_DTYPE, SupervisorState
from server.settings import Settings
from server.users.models import User

POSTGRES_URL_ENV = "SSP_REHAB_TEST_POSTGRES_URL"
TEST_SECRET = "test-secret-key-of-sufficient-length"
ADMIN_PASSWORD = "admin-password-1"
THERAPIST_PASSWORD = "therapist-password-1"


def run_columns(time_s: np.ndarray, forces: np.ndarray, cops: np.ndarray, state: np.ndarray | None = None) -> dict:
    """Telemetry columns for a run's balance measures: a run in motion throughout (unless `state` says otherwise)."""
    running = np.full(len(time_s), int(SupervisorState.RUNNING), dtype=np.uint8)
    return {"time_s": time_s, "session_time_s": time_s - time_s[0], "state": running if state is None else state,
            "plate_force_z_n": forces, "plate_cop_m": cops}  # fmt: skip


@dataclass
class Seed:
    """Accounts committed once per database, with tokens signed by the test key."""

    backend: str
    admin_id: int
    therapist_id: int
    admin_token: str
    therapist_token: str
    # A second therapist, for object-level authorisation: not in the care of the first one's patients.
    colleague_id: int
    colleague_token: str

    def headers(self, role: str = "therapist") -> dict[str, str]:
        token = {"admin": self.admin_token, "therapist": self.therapist_token, "colleague": self.colleague_token}[role]
        return {"Authorization": f"Bearer {token}"}


def _seed_accounts(engine: Engine, backend: str) -> Seed:
    signer = TokenSigner(TEST_SECRET.encode())
    expires = dt.datetime.now(dt.UTC) + dt.timedelta(days=1)
    tokens = {}
    with engine.begin() as connection:
        ids = {}
        for username, role, password in (
            ("admin", "admin", ADMIN_PASSWORD),
            ("therapist", "therapist", THERAPIST_PASSWORD),
            ("colleague", "therapist", THERAPIST_PASSWORD),
        ):
            user_id = connection.execute(
                User.__table__.insert()
                .values(
                    username=username,
                    full_name="",
                    role=role,
                    password_hash=hash_password(password),
                    is_active=True,
                    created_at=dt.datetime.now(dt.UTC),
                )
                .returning(User.__table__.c.id)
            ).scalar_one()
            session_id = new_session_id()
            connection.execute(
                AuthSession.__table__.insert().values(
                    id=session_id, user_id=user_id, created_at=dt.datetime.now(dt.UTC), expires_at=expires
                )
            )
            ids[username] = user_id
            tokens[username] = signer.issue(TokenClaims(session_id, user_id, int(expires.timestamp())))
    return Seed(
        backend, ids["admin"], ids["therapist"], tokens["admin"], tokens["therapist"], ids["colleague"],
        tokens["colleague"],
    )  # fmt: skip


def postgres_url_or_skip() -> str:
    url = os.environ.get(POSTGRES_URL_ENV)
    if not url:
        pytest.skip(
            f"PostgreSQL tests need {POSTGRES_URL_ENV} (e.g. postgresql+psycopg://postgres@127.0.0.1:5432/test)"
        )
    probe = create_engine(url)
    try:
        with probe.connect():
            pass
    except Exception as error:
        pytest.skip(f"PostgreSQL at {POSTGRES_URL_ENV} is unreachable: {type(error).__name__}: {error}".splitlines()[0])
    finally:
        probe.dispose()
    return url


@dataclass
class ScratchDatabase:
    """An empty database to migrate: a SQLite file, or a fresh schema in the test PostgreSQL database."""

    backend: str
    url: str
    engine: Engine
    drop: Callable[[], None]


def scratch_database(backend: str, directory: Path) -> ScratchDatabase:
    if backend == "sqlite":
        url = f"sqlite:///{directory / f'{uuid.uuid4().hex}.sqlite3'}"
        engine = create_database_engine(url)
        return ScratchDatabase(backend, url, engine, engine.dispose)
    base_url = postgres_url_or_skip()
    schema = f"ssp_rehab_test_{uuid.uuid4().hex[:12]}"
    admin = create_engine(base_url)
    with admin.begin() as connection:
        connection.execute(text(f'CREATE SCHEMA "{schema}"'))
    engine = create_database_engine(base_url, connect_args={"options": f"-csearch_path={schema}"})

    def drop() -> None:
        engine.dispose()
        with admin.begin() as connection:
            connection.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()

    separator = "&" if "?" in base_url else "?"
    return ScratchDatabase(backend, f"{base_url}{separator}options=-csearch_path%3D{schema}", engine, drop)


BACKENDS = ["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)]


@pytest.fixture(scope="session", params=BACKENDS)
def migrated(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Engine, Seed]]:
    scratch = scratch_database(request.param, tmp_path_factory.mktemp("db"))
    try:
        upgrade_database(scratch.engine)
        yield scratch.engine, _seed_accounts(scratch.engine, request.param)
    finally:
        scratch.drop()


@pytest.fixture
def seed(migrated: tuple[Engine, Seed]) -> Seed:
    return migrated[1]


@pytest.fixture
def database(migrated: tuple[Engine, Seed]) -> Iterator[Database]:
    """The app's database for one test: everything it writes is rolled back afterwards."""
    engine = migrated[0]
    connection = engine.connect()
    transaction = connection.begin()
    try:
        yield Database(engine, connection=connection)
    finally:
        transaction.rollback()
        connection.close()


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return Settings(
        _env_file=None,  # type: ignore[call-arg]
        data_dir=tmp_path,
        secret_key=TEST_SECRET,
        start_worker=False,
        telemetry_rate_hz=60.0,
        log_flush_interval_s=0.05,
    )


@pytest.fixture
def client(settings: Settings, database: Database) -> Iterator[TestClient]:
    """The service with no robot connected."""
    with TestClient(create_app(settings, database=database, worker=None)) as test_client:
        yield test_client


@dataclass
class FakeWorker:
    """Implements the agreed WorkerClient interface in memory: records commands, produces telemetry and events."""

    sample_rate_hz: float = 1000.0
    calls: list[tuple[str, tuple[Any, ...]]] = field(default_factory=list)
    refuse_with: Exception | None = None
    tick: int = 0
    _telemetry: list[np.ndarray] = field(default_factory=list)
    _events: list[dict[str, Any]] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    estopped: threading.Event = field(default_factory=threading.Event)
    estop_requests: int = 0  # as the control block's counter: every emergency stop requested
    estop_request_utc_s: float | None = None
    load_gate: threading.Event | None = None  # when set by a test, a load waits for it (a long check)
    loading: threading.Event = field(default_factory=threading.Event)  # a load is under way
    plan_index: int = 100  # the plan sample "played": a pause is checked ahead of it
    braking_resets: int = 0  # resets refused as the worker refuses them while an emergency stop's ramp runs

    def _command(self, name: str, *args: Any) -> None:
        if self.refuse_with is not None and name not in ("emergency_stop", "latest_state"):
            raise self.refuse_with
        with self._lock:
            self.calls.append((name, args))

    def start(self) -> None: ...
    def shutdown(self) -> None: ...

    def load_plan(self, plan: Any, report: dict[str, Any], estop_generation: int | None = None) -> None:
        self.loading.set()
        if self.load_gate is not None:
            assert self.load_gate.wait(60.0), "the test never ended the load"
        self._command("load_plan", plan, report)

    def start_motion(self, approach: Any, estop_generation: int | None = None) -> None:
        self._command("start_motion", approach)

    def pause(self, transition: Any) -> None:
        self._command("pause", transition)

    def resume(self, transition: Any) -> None:
        self._command("resume", transition)

    def stop(self) -> None:
        self._command("stop")

    def emergency_stop(self) -> None:
        self.estop_requests, self.estop_request_utc_s = self.estop_requests + 1, time.time()
        self._command("emergency_stop")
        self.estopped.set()

    def estop_request(self) -> tuple[int, float | None]:
        return self.estop_requests, self.estop_request_utc_s

    def reset(self) -> None:
        if self.braking_resets > 0:
            self.braking_resets -= 1
            raise TransitionRefused("reset", SupervisorState.ESTOP, STOP_RAMP_RUNNING)
        self._command("reset")

    def latest_state(self) -> dict[str, Any]:
        return {
            "state": "running",
            "tick": self.tick,
            "time_s": self.tick / self.sample_rate_hz,
            "measured_stance_pose": [0.0] * 6,  # standing at neutral
            "plan_index": self.plan_index,
        }

    def command_names(self) -> list[str]:
        with self._lock:
            return [name for name, _ in self.calls]

    def produce(self, samples: int) -> np.ndarray:
        """Append `samples` ticks of telemetry, as the worker's ring would hold them."""
        records = np.zeros(samples, dtype=TELEMETRY_DTYPE)
        ticks = np.arange(self.tick, self.tick + samples)
        records["tick"] = ticks
        records["time_s"] = ticks / self.sample_rate_hz
        if "utc_s" in records.dtype.names:
            records["utc_s"] = time.time() - (samples - 1 - np.arange(samples)) / self.sample_rate_hz
        records["stance_pose"][:, 1] = 0.01 * np.sin(ticks / self.sample_rate_hz)
        records["plate_force_z_n"] = 320.0
        records["harness_load_n"] = 12.0
        with self._lock:
            self.tick += samples
            self._telemetry.append(records)
        return records

    def emit_event(self, kind: str, **details: Any) -> None:
        with self._lock:
            self._events.append(
                {
                    "kind": kind,
                    "tick": self.tick,
                    "tick_time_s": self.tick / self.sample_rate_hz,
                    "utc": dt.datetime.now(dt.UTC).isoformat(),
                    "detector": "test",
                    "details": details,
                }
            )

    def drain_telemetry(self) -> np.ndarray:
        with self._lock:
            drained = np.concatenate(self._telemetry) if self._telemetry else np.zeros(0, dtype=TELEMETRY_DTYPE)
            self._telemetry = []
        return drained

    def drain_events(self) -> list[dict[str, Any]]:
        with self._lock:
            drained, self._events = self._events, []
        return drained


@pytest.fixture
def fake_worker() -> FakeWorker:
    return FakeWorker()


@pytest.fixture
def robot_client(settings: Settings, database: Database, fake_worker: FakeWorker) -> Iterator[TestClient]:
    """The service with the fake worker connected (and the session recorder running)."""
    with TestClient(create_app(settings, database=database, worker=fake_worker)) as test_client:
        yield test_client


def wait_until(condition: Callable[[], Any], timeout_s: float = 5.0, period_s: float = 0.01) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(period_s)
    raise AssertionError("condition not met in time")


PREVIEW_WAIT_S = 120.0  # a short preview takes a second; the preview process's start-up many at load 20


def finished_preview(
    get: Callable[[str], Any], started: Any, timeout_s: float = PREVIEW_WAIT_S, seen: list[dict[str, Any]] | None = None
) -> dict[str, Any]:
    """The preview job that `started` (the answer of `POST /prescriptions/previews`) names, once it has ended,
    polled at its Location through `get` (which takes the path under /api/v1); `seen` collects every answer."""
    assert started.status_code == 202, started.text
    location = started.headers["location"]
    assert location == f"/api/v1/prescriptions/previews/{started.json()['preview_id']}", location

    def ended() -> dict[str, Any] | None:
        answer = get(location.removeprefix("/api/v1"))
        assert answer.status_code == 200, answer.text
        job: dict[str, Any] = answer.json()
        if seen is not None:
            seen.append(job)
        return job if job["state"] != "planning" else None

    job: dict[str, Any] = wait_until(ended, timeout_s, period_s=0.02)
    return job


# --- records most tests need ------------------------------------------------------------------------

PATIENT = {
    "identifier": "MRN-4711",
    "name": "Greta Testperson",
    "date_of_birth": "1950-02-03",
    "sex": "female",
    "height_m": 1.65,
    "body_mass_kg": 60.0,
    "diagnosis": "stroke",
    "affected_side": "left",
}
SEGMENT = {
    "cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.5},
    "duration_s": 30.0,
    "limits": {"tilt_max_rad": 0.2},
}


@dataclass
class Booked:
    patient_id: int
    prescription_id: int
    session_id: int


def create_patient(client: TestClient, headers: dict[str, str], **overrides: Any) -> int:
    response = client.post("/api/v1/patients", json={**PATIENT, **overrides}, headers=headers)
    assert response.status_code == 201, response.text
    return int(response.json()["id"])


def create_prescription(client: TestClient, headers: dict[str, str], patient_id: int) -> int:
    body = {"patient_id": patient_id, "name": "Lateral sway", "segments": [SEGMENT]}
    response = client.post("/api/v1/prescriptions", json=body, headers=headers)
    assert response.status_code == 201, response.text
    return int(response.json()["id"])


def book(
    client: TestClient,
    headers: dict[str, str],
    *,
    patient_id: int,
    prescription_id: int,
    start: str = "2031-05-06T09:00:00+00:00",
    robot: str = "twin-1",
    duration_s: int = 1800,
    **extra: Any,
) -> Any:
    body = {
        "patient_id": patient_id,
        "prescription_id": prescription_id,
        "robot": robot,
        "start": start,
        "duration_s": duration_s,
        **extra,
    }
    return client.post("/api/v1/sessions", json=body, headers=headers)


def booked_session(
    client: TestClient,
    headers: dict[str, str],
    *,
    start: str = "2031-05-06T09:00:00+00:00",
    robot: str = "twin-1",
    **patient_overrides: Any,
) -> Booked:
    patient_id = create_patient(client, headers, **patient_overrides)
    prescription_id = create_prescription(client, headers, patient_id)
    response = book(client, headers, patient_id=patient_id, prescription_id=prescription_id, start=start, robot=robot)
    assert response.status_code == 201, response.text
    return Booked(patient_id, prescription_id, response.json()[0]["id"])


@pytest.fixture
def console(tmp_path: Path) -> Iterator[Console]:
    """A real console (`serve` and its robot daemon as separate processes) in a fresh data directory; a
    module that needs other options defines its own."""
    instance = Console(tmp_path / "console")
    instance.start()
    try:
        yield instance
    finally:
        instance.stop()


@pytest.fixture(scope="module")
def shared_console(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Console]:
    """One real console for a module's tests that leave its processes whole (none killed or left stopped):
    starting one costs seconds to minutes on the loaded test machine. Take it through `resting_console`."""
    instance = Console(tmp_path_factory.mktemp("shared") / "console")
    instance.start()
    try:
        yield instance
    finally:
        instance.stop()


@pytest.fixture
def resting_console(shared_console: Console) -> Console:
    """The module's shared console with its robot at rest, as a fresh one starts: what an earlier test left
    running is stopped, a latched stop reset and every stop that moved the patient acknowledged."""
    bring_to_rest(shared_console)
    return shared_console


def bring_to_rest(console: Console) -> None:
    def open_runs() -> list[int]:
        with console.database() as connection:
            query = text("SELECT scheduled_session_id FROM session_runs WHERE state != 'ended'")
            return list(connection.execute(query).scalars())

    for session_id in open_runs():
        console.post(f"/sessions/{session_id}/stop")

    def at_rest() -> bool:
        state = console.get("/robot/state")
        if state.status_code != 200:
            return False
        robot = state.json()
        if robot["state"] in ("idle", "ready") and not robot["estop_latched"]:
            return not open_runs()
        if robot["state"] in ("stopped", "estop", "fault"):
            console.post("/robot/reset")  # refused while a stop ramp still runs: asked again at the next look
        return False

    wait_for(at_rest, EVENT_TIMEOUT_S, "the shared console's robot to come to rest", 0.1)
    wait_for(lambda: console.acknowledge_pending() is None, EVENT_TIMEOUT_S, "every stop acknowledged", 0.1)


def fallen_run(database: Database, booking: dict[str, Any]) -> int:
    """A run that a fall ended, as the recorder writes it: what the run-review bodies act on."""
    from sqlalchemy import select

    from server.prescriptions.models import PrescriptionVersion
    from server.robotd.models import SessionRun

    with database.session() as session:
        version_id = session.scalar(
            select(PrescriptionVersion.id).where(PrescriptionVersion.prescription_id == booking["prescription_id"])
        )
        run = SessionRun(scheduled_session_id=booking["id"], prescription_version_id=version_id, robot=booking["robot"],
                         state="ended", outcome="fall", ended_at=dt.datetime.now(dt.UTC))  # fmt: skip
        session.add(run)
        session.commit()
        return int(run.id)
