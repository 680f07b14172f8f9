"""The robot daemon's parts on their own: one daemon per robot (the lock), the run journal, recovery of a
run a crash left open, the status record's staleness, and the CSV cue's size limit."""

from __future__ import annotations

import datetime as dt
import os
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import select

from core.plan.prescription import CSV_CUE_MAX_BYTES, PrescriptionError, parse_prescription
from server.db import Database
from server.realtime.telemetry import TELEMETRY_DTYPE
from server.robotd.journal import RunJournal, read_journal
from server.robotd.models import SessionEvent, SessionRun, TelemetryChunk
from server.robotd.process import AlreadyRunning, take_lock
from server.robotd.recovery import recover_open_runs
from server.robotd.status import DAEMON_STALE_S, DaemonState, RobotPaths, StatusBlock, daemon_running
from tests.server.conftest import FakeWorker, Seed, booked_session, wait_until


def test_one_daemon_per_robot(tmp_path: Path) -> None:
    paths = RobotPaths(tmp_path, "twin-1")
    assert not daemon_running(paths)
    held = take_lock(paths)
    try:
        paths.pid.write_text("4242\n")
        assert daemon_running(paths)
        with pytest.raises(AlreadyRunning, match="already running \\(pid 4242\\)"):
            take_lock(paths)
        os.close(take_lock(RobotPaths(tmp_path, "twin-2")))  # another robot has its own daemon
    finally:
        os.close(held)
    assert not daemon_running(paths)
    with pytest.raises(ValueError, match=r"robot = '\.\./x'"):
        RobotPaths(tmp_path, "../x")


def test_the_journal_keeps_every_whole_record_and_line(tmp_path: Path) -> None:
    journal = RunJournal(tmp_path, 7, TELEMETRY_DTYPE)
    records = np.zeros(5, TELEMETRY_DTYPE)
    records["tick"] = np.arange(5)
    journal.append_telemetry(records)
    journal.append_events([{"kind": "fall", "utc": "2026-12-01T10:00:00+00:00", "details": {"harness_load_n": 300.0}}])
    journal.close()
    with (journal.directory / "telemetry.bin").open("ab") as torn:  # a crash in the middle of a write
        torn.write(b"\x01\x02\x03")
    with (journal.directory / "events.jsonl").open("a") as torn:
        torn.write('{"kind": "contr')
    read, events = read_journal(tmp_path, 7)
    assert read is not None and list(read["tick"]) == [0, 1, 2, 3, 4]
    assert [e["kind"] for e in events] == ["fall"]


def test_a_run_left_open_is_closed_interrupted_at_its_last_record_with_what_the_journal_holds(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker, database: Database, tmp_path: Path
) -> None:
    booked = booked_session(robot_client, seed.headers())
    run_id = robot_client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers()).json()["id"]
    fake_worker.produce(200)
    wait_until(lambda: robot_client.get(f"/api/v1/runs/{run_id}", headers=seed.headers()).json()["sample_count"] == 200)
    robot_client.app.state.robot.daemon.run = None  # the daemon "dies": the run stays open in the database
    # What the dead daemon's journal held beyond the database: 100 more samples and its last events.
    journal = RunJournal(tmp_path, run_id, TELEMETRY_DTYPE)
    tail = np.zeros(300, TELEMETRY_DTYPE)
    tail["tick"] = np.arange(300)
    last_utc = time.time() + 1.0  # after everything the database holds
    tail["utc_s"] = np.linspace(last_utc - 1.0, last_utc, 300)
    journal.append_telemetry(tail)
    lost_event = {"kind": "service_lost", "utc": dt.datetime.fromtimestamp(last_utc - 0.5, dt.UTC).isoformat(),
                  "tick": 250, "tick_time_s": 0.25, "details": {}}  # fmt: skip
    journal.append_events([lost_event])
    journal.close()
    assert recover_open_runs(database=database, robot="twin-1", journal_dir=tmp_path) == [run_id]
    assert recover_open_runs(database=database, robot="twin-1", journal_dir=tmp_path) == []  # idempotent
    with database.session() as session:
        run = session.get(SessionRun, run_id)
        assert run is not None and (run.state, run.outcome) == ("ended", "interrupted")
        assert abs(run.ended_at.replace(tzinfo=dt.UTC).timestamp() - last_utc) < 0.01  # the true time
        assert run.sample_count == 300
        stored = session.scalars(select(TelemetryChunk.sample_count).where(TelemetryChunk.run_id == run_id)).all()
        assert sum(stored) == 300
        kinds = session.scalars(select(SessionEvent.kind).where(SessionEvent.run_id == run_id)).all()
        assert kinds.count("service_lost") == 1 and kinds[-1] == "run_ended"
    assert not (tmp_path / f"run-{run_id}").exists()
    second = booked_session(robot_client, seed.headers(), identifier="MRN-2", start="2031-05-06T10:00:00+00:00")
    # The interruption moved the patient: acknowledged before the robot starts again (issue 20, build 9).
    acknowledged = robot_client.post(f"/api/v1/runs/{run_id}/acknowledge", json={}, headers=seed.headers())
    assert acknowledged.status_code == 200, acknowledged.text
    free = robot_client.post(f"/api/v1/sessions/{second.session_id}/start", headers=seed.headers())
    assert free.status_code == 200, free.text


def test_a_refused_start_for_another_robot_leaves_the_running_run_recording(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    first = booked_session(robot_client, seed.headers())
    run_id = robot_client.post(f"/api/v1/sessions/{first.session_id}/start", headers=seed.headers()).json()["id"]
    other = booked_session(
        robot_client, seed.headers(), identifier="MRN-2", robot="twin-2", start="2031-05-06T10:00:00+00:00"
    )
    refused = robot_client.post(f"/api/v1/sessions/{other.session_id}/start", headers=seed.headers())
    assert refused.status_code == 409 and "booked on robot 'twin-2'" in refused.json()["detail"]
    fake_worker.produce(300)
    fake_worker.emit_event("limit_hit", limit="tilt_max_rad")
    wait_until(lambda: robot_client.get(f"/api/v1/runs/{run_id}", headers=seed.headers()).json()["sample_count"] == 300)
    events = robot_client.get(f"/api/v1/runs/{run_id}/events", headers=seed.headers()).json()
    assert "limit_hit" in [e["kind"] for e in events]  # filed under the run, not under none
    assert fake_worker.command_names() == ["load_plan", "start_motion"]  # the refusal never reached it


def test_a_silent_status_record_reads_as_absent() -> None:
    block = StatusBlock()
    try:
        block.publish(DaemonState.READY, "backend kinematic", 1234, (5, 6))
        status = block.read()
        assert (status.state, status.active_run_id, status.active_session_id) == (DaemonState.READY, 5, 6)
        time.sleep(DAEMON_STALE_S * 2)
        stale = block.read()
        assert stale.state is DaemonState.ABSENT and "stopped answering" in stale.reason
    finally:
        block.close()


def test_a_csv_cue_over_the_size_limit_is_refused_naming_the_field() -> None:
    segment = {"cue": {"kind": "csv_replay", "csv": "x" * (CSV_CUE_MAX_BYTES + 1)}, "duration_s": 10.0}
    with pytest.raises(PrescriptionError) as refused:
        parse_prescription({"segments": [segment]})
    assert refused.value.field == "segments[0].cue.csv" and str(CSV_CUE_MAX_BYTES) in refused.value.limit


def test_a_start_that_cannot_be_recorded_stops_the_robot_again_and_says_why(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker, monkeypatch: pytest.MonkeyPatch
) -> None:
    from sqlalchemy.exc import OperationalError

    from server.robotd import runs

    booked = booked_session(robot_client, seed.headers())

    def read_only(**_: object) -> None:
        raise OperationalError("INSERT INTO session_runs", {}, Exception("attempt to write a readonly database"))

    monkeypatch.setattr(runs, "record_start", read_only)
    response = robot_client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers())
    assert response.status_code == 503 and "readonly database" in response.json()["detail"], response.text
    assert "stopped again" in response.json()["detail"]
    assert fake_worker.command_names() == ["load_plan", "start_motion", "stop"]
    assert robot_client.app.state.robot.active_run() is None
