"""Issue 20, defects 6, 7 and part of 19: the database goes away in the middle of a session.

Stop, pause and the robot's state must not need it (the daemon decides, journals and answers; the database
catches up from the daemon afterwards), /health must say the database is unreachable, and the 503 of a data
route must not name the database's host, port or file. A real outage: on PostgreSQL, a TCP proxy (loopback
only) in front of the test server that closes every connection and refuses new ones; on SQLite, another
connection holding the write lock, as a stuck process or a backup would.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import socket
import sqlite3
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import Engine, make_url, select

from benchmarks.fault_harness import in_background
from core.robot import default_twin
from server.app import create_app
from server.auth.safe_commands import TOKEN_ONLY, VERIFIED
from server.db import Database, create_database_engine, upgrade_database
from server.realtime.supervisor import SupervisorConfig
from server.realtime.telemetry import TELEMETRY_DTYPE
from server.robotd.daemon import RobotDaemon
from server.robotd.journal import RunJournal, read_decisions
from server.robotd.link import LocalLink
from server.robotd.models import SessionEvent, SessionRun, TelemetryChunk
from server.robotd.plan_store import PlanStore
from server.robotd.planner import InlinePlanner
from server.robotd.records import decode_chunk
from server.robotd.recovery import recover_open_runs
from server.settings import Settings
from tests.server.conftest import (
    ADMIN_PASSWORD,
    FakeWorker,
    Seed,
    _seed_accounts,
    booked_session,
    scratch_database,
    wait_until,
)

OUTAGE_WAIT_S = 60.0  # generous: the machine is loaded; every wait below ends on an event


class OutageProxy:
    """A loopback TCP proxy to `target`; `outage()` closes every connection through it and refuses new ones
    (accepted and closed at once) until it ends."""

    def __init__(self, target: tuple[str, int]) -> None:
        self.target = target
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.down = threading.Event()
        self._open: set[socket.socket] = set()
        self._lock = threading.Lock()
        self._closed = False
        threading.Thread(target=self._accept_forever, daemon=True).start()

    def _accept_forever(self) -> None:
        while not self._closed:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            if self.down.is_set():
                client.close()
                continue
            try:
                upstream = socket.create_connection(self.target)
            except OSError:
                client.close()
                continue
            with self._lock:
                self._open.update((client, upstream))
            for source, sink in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(source, sink), daemon=True).start()

    def _pipe(self, source: socket.socket, sink: socket.socket) -> None:
        with contextlib.suppress(OSError):
            while data := source.recv(65536):
                sink.sendall(data)
        for end in (source, sink):
            with contextlib.suppress(OSError):
                end.shutdown(socket.SHUT_RDWR)

    def _cut_all(self) -> None:
        with self._lock:
            for connection in self._open:
                with contextlib.suppress(OSError):
                    connection.shutdown(socket.SHUT_RDWR)
                with contextlib.suppress(OSError):
                    connection.close()
            self._open.clear()

    @contextlib.contextmanager
    def outage(self) -> Iterator[None]:
        self.down.set()
        self._cut_all()
        try:
            yield
        finally:
            self.down.clear()

    def close(self) -> None:
        self._closed = True
        self.listener.close()
        self._cut_all()


@contextlib.contextmanager
def sqlite_write_lock(database_file: Path) -> Iterator[None]:
    """Another connection holds SQLite's write lock: every write of the console waits, then fails."""
    holder = sqlite3.connect(database_file, isolation_level=None, check_same_thread=False)
    try:
        holder.execute("BEGIN IMMEDIATE")
        yield
    finally:
        holder.execute("ROLLBACK")
        holder.close()


@contextlib.contextmanager
def console_on(database: Database, settings: Settings, worker: FakeWorker, journal_dir: Path) -> Iterator[TestClient]:
    """The console with an in-process robot daemon that journals, as the daemon process does."""
    app = create_app(settings, database=database, worker=None)
    twin = default_twin()
    daemon = RobotDaemon(
        robot=settings.robot,
        worker=worker,  # type: ignore[arg-type]
        database=database,
        journal_dir=journal_dir,
        planner=InlinePlanner(twin, settings.control_rate_hz, SupervisorConfig()),
        twin=twin,
        plan_store=PlanStore(journal_dir.parent / "plans"),
        chunk_period_s=0.05,
        shutdown_wait_s=0.0,
    )
    with TestClient(app) as client:
        link = LocalLink(daemon)
        link.open()
        app.state.robot = link
        try:
            yield client
        finally:
            app.state.robot = None
            link.close()


@contextlib.contextmanager
def outage_database(backend: str, directory: Path) -> Iterator[tuple[str, Engine, Seed, Any]]:
    """(backend, the console's engine, seeded accounts, a context manager that takes the database away)."""
    scratch = scratch_database(backend, directory)
    try:
        upgrade_database(scratch.engine)
        seed = _seed_accounts(scratch.engine, backend)
        if backend == "sqlite":
            engine = create_database_engine(scratch.url)
            outage: Any = lambda: sqlite_write_lock(Path(make_url(scratch.url).database or ""))  # noqa: E731
            try:
                yield backend, engine, seed, outage
            finally:
                engine.dispose()
        else:
            url = make_url(scratch.url)
            proxy = OutageProxy((url.host or "127.0.0.1", url.port or 5432))
            engine = create_database_engine(url.set(host="127.0.0.1", port=proxy.port))
            try:
                yield backend, engine, seed, proxy.outage
            finally:
                engine.dispose()
                proxy.close()
    finally:
        scratch.drop()


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def outage_setup(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[str, Engine, Seed, Any]]:
    with outage_database(request.param, tmp_path) as setup:
        yield setup


def answer_during_outage(function: Any) -> Any:
    """The answer, which must come while the database is still away (the outage lasts until it comes)."""
    thread, result = in_background(function)
    thread.join(OUTAGE_WAIT_S)
    assert result, f"no answer within {OUTAGE_WAIT_S} s while the database was away"
    if isinstance(result[0], Exception):
        raise result[0]
    return result[0]


def stored_run(engine: Engine, run_id: int) -> tuple[SessionRun, list[SessionEvent], np.ndarray]:
    with Database(engine).session() as session:
        run = session.get(SessionRun, run_id)
        assert run is not None
        events = list(
            session.scalars(select(SessionEvent).where(SessionEvent.run_id == run_id).order_by(SessionEvent.id))
        )
        chunks = session.scalars(
            select(TelemetryChunk.data).where(TelemetryChunk.run_id == run_id).order_by(TelemetryChunk.sequence)
        ).all()
    ticks = np.concatenate([decode_chunk(blob)["tick"] for blob in chunks]) if chunks else np.zeros(0, np.int64)
    return run, events, ticks


def test_stop_pause_and_the_robot_state_answer_while_the_database_is_down(
    outage_setup: tuple[str, Engine, Seed, Any], settings: Settings, tmp_path: Path
) -> None:
    backend, engine, seed, outage = outage_setup
    worker = FakeWorker()
    journal_dir = tmp_path / "journal"
    headers = seed.headers("therapist")
    with console_on(Database(engine), settings, worker, journal_dir) as client:
        booked = booked_session(client, headers)
        started = client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=headers)
        assert started.status_code == 200, started.text
        run_id = started.json()["id"]
        produced = [worker.produce(200)]
        wait_until(lambda: stored_run(engine, run_id)[0].sample_count > 0, OUTAGE_WAIT_S)

        with outage():
            produced.append(worker.produce(300))
            state = answer_during_outage(lambda: client.get("/api/v1/robot/state", headers=headers))
            assert state.status_code == 200, state.text
            paused = answer_during_outage(
                lambda: client.post(f"/api/v1/sessions/{booked.session_id}/pause", headers=headers)
            )
            assert paused.status_code == 200, paused.text
            assert paused.json()["state"] == "paused", paused.json()
            produced.append(worker.produce(300))
            stopped = answer_during_outage(
                lambda: client.post(f"/api/v1/sessions/{booked.session_id}/stop", headers=headers)
            )
            assert stopped.status_code == 200, stopped.text
            answer = stopped.json()
            assert (answer["id"], answer["state"], answer["outcome"]) == (run_id, "ended", "stopped"), answer
            assert answer["stopped_by_id"] == seed.therapist_id, answer
            assert worker.command_names()[-2:] == ["pause", "stop"], worker.command_names()
            journalled = read_decisions(journal_dir, run_id)  # before the database heard of them
            assert [(d["decision"], d["user_id"]) for d in journalled] == [
                ("pause", seed.therapist_id),
                ("end", seed.therapist_id),
            ], journalled
            assert journalled[-1]["outcome"] == "stopped", journalled
            produced.append(worker.produce(100))  # the controlled stop's last samples
            worker.emit_event("drives_disabled")

        # The database is back: it catches up with everything the daemon decided and recorded meanwhile.
        wait_until(lambda: not (journal_dir / f"run-{run_id}").exists(), OUTAGE_WAIT_S)
        run, events, ticks = stored_run(engine, run_id)
    expected = np.concatenate([records["tick"] for records in produced])
    assert (run.state, run.outcome, run.stopped_by_id) == ("ended", "stopped", seed.therapist_id)
    assert run.ended_at is not None
    assert run.sample_count == len(expected) and np.array_equal(ticks, expected), (run.sample_count, len(ticks))
    kinds = [event.kind for event in events]
    assert kinds == ["start", "pause", "stop", "run_ended", "drives_disabled"], kinds
    by_kind = {event.kind: event for event in events}
    assert by_kind["pause"].user_id == seed.therapist_id and by_kind["stop"].user_id == seed.therapist_id
    # What the request proved is recorded with the command: a login the database confirmed, or (the
    # database unreachable, as on PostgreSQL here) the signed token alone.
    credentials = {by_kind[kind].details.get("credential") for kind in ("pause", "stop")}
    assert credentials <= {VERIFIED, TOKEN_ONLY} and (backend != "postgresql" or credentials == {TOKEN_ONLY}), (
        credentials
    )


@pytest.mark.postgres
def test_health_says_degraded_while_the_database_is_unreachable_and_the_503_names_no_host(
    settings: Settings, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with (
        outage_database("postgresql", tmp_path) as (_, engine, seed, outage),
        TestClient(create_app(settings, database=Database(engine), worker=None)) as client,
    ):
        port = str(engine.url.port)
        assert client.get("/api/v1/health").json()["status"] == "ok"
        with outage():
            health = wait_until(
                lambda: (h := client.get("/api/v1/health").json())["status"] == "degraded" and h, OUTAGE_WAIT_S
            )
            assert health["database"] == {"reachable": False, "writable": False, "reason": health["reasons"][0]}
            assert health["reasons"][0].startswith("the database is unreachable"), health
            with caplog.at_level(logging.ERROR, logger="server.app"):
                refused = client.get("/api/v1/patients", headers=seed.headers())
            assert refused.status_code == 503, refused.text
            assert refused.json() == {"detail": "the database is unavailable: nothing was written"}
            assert port in caplog.text, "the service's log must keep the detail the browser no longer sees"
        health = wait_until(lambda: (h := client.get("/api/v1/health").json())["status"] == "ok" and h, OUTAGE_WAIT_S)
        assert health["database"] == {"reachable": True, "writable": True, "reason": None}, health


def test_a_read_only_database_503_names_no_file(tmp_path: Path, settings: Settings) -> None:
    database_file = tmp_path / "private-name.sqlite3"
    writable = create_database_engine(f"sqlite:///{database_file}")
    upgrade_database(writable)
    _seed_accounts(writable, "sqlite")
    writable.dispose()
    read_only = create_database_engine(f"sqlite:///file:{database_file}?mode=ro&uri=true")
    try:
        with TestClient(create_app(settings, database=Database(read_only), worker=None)) as client:
            body = {"username": "admin", "password": ADMIN_PASSWORD}
            refused = client.post("/api/v1/auth/login", json=body)
            assert refused.status_code == 503, refused.text
            assert refused.json() == {"detail": "the database is read-only: nothing was written"}
            health = client.get("/api/v1/health").json()
            assert "private-name" not in str(health) and health["status"] == "degraded", health
    finally:
        read_only.dispose()


def test_a_stop_the_database_never_heard_of_is_recovered_from_the_journal_as_decided(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker, database: Database, tmp_path: Path
) -> None:
    """The daemon journalled pause and stop during an outage, then died before the database returned:
    the next start closes the run as the daemon decided, not as `interrupted`."""
    headers = seed.headers()
    booked = booked_session(robot_client, headers)
    run_id = robot_client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=headers).json()["id"]
    robot_client.app.state.robot.daemon.run = None  # type: ignore[attr-defined]  # the daemon "dies"
    journal = RunJournal(tmp_path, run_id, TELEMETRY_DTYPE)
    paused_at = dt.datetime.now(dt.UTC) + dt.timedelta(seconds=1)
    stopped_at = paused_at + dt.timedelta(seconds=2)
    journal.append_decision(
        {"decision": "pause", "user_id": seed.therapist_id, "credential": TOKEN_ONLY, "utc": paused_at, "tick": 5}
    )
    journal.append_decision(
        {
            "decision": "end",
            "outcome": "stopped",
            "reason": "stopped by the operator",
            "user_id": seed.therapist_id,
            "credential": TOKEN_ONLY,
            "utc": stopped_at,
            "tick": 9,
            "tick_time_s": 0.009,
        }
    )
    with (journal.directory / "decisions.jsonl").open("a") as torn:  # the daemon died mid-write
        torn.write('{"decision": "res')
    journal.close()
    assert recover_open_runs(database=database, robot="twin-1", journal_dir=tmp_path) == [run_id]
    with database.session() as session:
        run = session.get(SessionRun, run_id)
        assert run is not None
        assert (run.state, run.outcome, run.stopped_by_id) == ("ended", "stopped", seed.therapist_id)
        assert run.ended_at == stopped_at
        events = session.scalars(select(SessionEvent).where(SessionEvent.run_id == run_id)).all()
        by_kind = {event.kind: event for event in events}
    # The daemon died after deciding the stop: recovery says so (defect 18) and keeps what it decided.
    assert sorted(by_kind) == ["daemon_lost", "pause", "run_ended", "start", "stop"], sorted(by_kind)
    assert by_kind["pause"].user_id == seed.therapist_id and by_kind["pause"].utc == paused_at
    assert by_kind["stop"].details == {"credential": TOKEN_ONLY} and by_kind["stop"].tick == 9
    assert by_kind["run_ended"].details["outcome"] == "stopped"
    assert not (tmp_path / f"run-{run_id}").exists()


@pytest.mark.slow
def test_a_real_console_stops_during_a_database_outage_and_the_records_catch_up(tmp_path: Path) -> None:
    """`serve` and its robot daemon as processes (kinematic backend, the real worker), SQLite's write lock
    held by another process's connection while the operator stops: the stop answers 200, the robot stops,
    and once the lock is gone the run's end, events and every sample reach the database."""
    from benchmarks.fault_harness import EVENT_TIMEOUT_S, Console, wait_for

    console = Console(tmp_path / "console")
    console.start()
    try:
        session_id = console.book()
        started = console.post(f"/sessions/{session_id}/start")
        assert started.status_code == 200, started.text
        run_id = started.json()["id"]
        console.wait_moving()
        wait_for(lambda: console.run(run_id)["sample_count"] > 0, EVENT_TIMEOUT_S, "samples in the database", 0.1)
        with sqlite_write_lock(console.data_dir / "ssp-rehab.sqlite3"):
            stopped = answer_during_outage(lambda: console.post(f"/sessions/{session_id}/stop"))
            assert stopped.status_code == 200, stopped.text
            assert (stopped.json()["state"], stopped.json()["outcome"]) == ("ended", "stopped"), stopped.json()
            wait_for(
                lambda: console.get("/robot/state").json().get("state") in ("stopped", "idle"),
                EVENT_TIMEOUT_S,
                "the robot to stop while the database is locked",
            )
        journal = console.data_dir / "runs" / console.robot / f"run-{run_id}"
        wait_for(lambda: not journal.exists(), EVENT_TIMEOUT_S * 2, "the database to catch up", 0.2)
        run = console.run_row(run_id)
        assert (run["state"], run["outcome"]) == ("ended", "stopped"), run
        count, first_tick, last_tick = console.telemetry_ticks(run_id)
        assert count == run["sample_count"] == last_tick - first_tick + 1, (count, run["sample_count"], first_tick)
        kinds = [event["kind"] for event in console.events(run_id)]
        assert {"start", "stop", "run_ended", "drives_disabled"} <= set(kinds), kinds
    finally:
        console.stop()
