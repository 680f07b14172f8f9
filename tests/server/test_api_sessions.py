"""Run control through the worker interface (a fake implementing the agreed WorkerClient), the emergency
stop, the session recorder (durable telemetry chunks + events), the telemetry WebSocket, and exports."""

from __future__ import annotations

import io
import json
import threading
import zipfile

import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from server.db import Database
from server.robotd.records import terminal_outcome_of
from tests.server.conftest import PATIENT, Booked, FakeWorker, Seed, booked_session, wait_until


def runs(client: TestClient, seed: Seed, booked: Booked) -> list[dict]:
    return client.get(f"/api/v1/sessions/{booked.session_id}/runs", headers=seed.headers()).json()


def events(client: TestClient, seed: Seed, run_id: int) -> list[dict]:
    return client.get(f"/api/v1/runs/{run_id}/events", headers=seed.headers()).json()


def start(client: TestClient, seed: Seed, booked: Booked) -> dict:
    response = client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers())
    assert response.status_code == 200, response.text
    return response.json()


def test_without_a_robot_run_control_answers_503_and_records_still_work(client: TestClient, seed: Seed) -> None:
    booked = booked_session(client, seed.headers())
    for path in ("start", "pause", "resume", "stop"):
        response = client.post(f"/api/v1/sessions/{booked.session_id}/{path}", headers=seed.headers())
        assert response.status_code == 503 and "no robot connected" in response.json()["detail"]
    assert client.post("/api/v1/estop", headers=seed.headers()).status_code == 503
    assert client.get("/api/v1/robot/state", headers=seed.headers()).status_code == 503
    assert runs(client, seed, booked) == []
    with client.websocket_connect(f"/api/v1/sessions/{booked.session_id}/telemetry", headers=seed.headers()) as socket:
        assert "no robot connected" in socket.receive_json()["detail"]


def test_start_loads_the_booked_version_and_anthropometrics_only(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    booked = booked_session(robot_client, seed.headers())
    run = start(robot_client, seed, booked)
    assert run["state"] == "running" and run["started_by_id"] == seed.therapist_id
    (name, (plan, report)), (second, (approach,)) = fake_worker.calls
    assert (name, second) == ("load_plan", "start_motion")
    version = robot_client.get(
        f"/api/v1/prescriptions/{booked.prescription_id}/versions/1", headers=seed.headers()
    ).json()
    segments = version["content"]["segments"]
    assert [dict(s.cue_spec) for s in plan.segments] == [s["cue"] for s in segments]
    assert [s.duration_s for s in plan.segments] == [s["duration_s"] for s in segments]
    assert run["prescription_version_id"] == version["id"]
    assert (plan.patient.body_mass_kg, plan.patient.height_m) == (60.0, 1.65)
    # The worker gets the checked plan and the checked approach from where the platform stands.
    assert report["samples"] == plan.played.samples and approach.kind == "approach"
    assert [e["kind"] for e in events(robot_client, seed, run["id"])] == ["start"]


def test_pause_resume_stop_follow_the_run_state(robot_client: TestClient, seed: Seed, fake_worker: FakeWorker) -> None:
    booked = booked_session(robot_client, seed.headers())
    base = f"/api/v1/sessions/{booked.session_id}"
    assert robot_client.post(f"{base}/pause", headers=seed.headers()).status_code == 409  # nothing running
    run = start(robot_client, seed, booked)
    assert robot_client.post(f"{base}/resume", headers=seed.headers()).status_code == 409  # not paused
    assert robot_client.post(f"{base}/pause", headers=seed.headers()).json()["state"] == "paused"
    assert robot_client.post(f"{base}/resume", headers=seed.headers()).json()["state"] == "running"
    stopped = robot_client.post(f"{base}/stop", headers=seed.headers(role="admin")).json()
    assert (stopped["state"], stopped["outcome"], stopped["stopped_by_id"]) == ("ended", "stopped", seed.admin_id)
    assert stopped["ended_at"] is not None
    assert fake_worker.command_names() == ["load_plan", "start_motion", "pause", "resume", "stop"]
    kinds = ["start", "pause", "resume", "stop", "run_ended"]  # the robot daemon records every end as run_ended
    assert [e["kind"] for e in events(robot_client, seed, run["id"])] == kinds
    motion = robot_client.get(
        "/api/v1/audit", params={"resource_type": "session_run"}, headers=seed.headers("admin")
    ).json()
    assert [e["details"]["command"] for e in reversed(motion)] == ["start", "pause", "resume", "stop"]


def test_one_robot_runs_one_session_at_a_time(robot_client: TestClient, seed: Seed) -> None:
    first = booked_session(robot_client, seed.headers())
    second = booked_session(robot_client, seed.headers(), identifier="MRN-2", start="2031-05-06T10:00:00+00:00")
    start(robot_client, seed, first)
    busy = robot_client.post(f"/api/v1/sessions/{second.session_id}/start", headers=seed.headers())
    assert busy.status_code == 409 and "busy" in busy.json()["detail"]


def test_a_refused_prescription_is_a_422_and_leaves_no_run(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    prescription = pytest.importorskip("core.plan.check")
    booked = booked_session(robot_client, seed.headers())
    breaches = {"kinematic_breaches": {"tilt": [[2.5, 2.75]]}, "singularity": {"worst_condition": 12.0}}
    fake_worker.refuse_with = prescription.PrescriptionRejected(
        0, 2.5, "tilt_max_rad", 0.31, "tilt over the limit", breaches
    )
    response = robot_client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers())
    assert response.status_code == 422
    detail = response.json()["detail"][0]
    assert detail["loc"] == ["body", "segments[0]"] and "tilt_max_rad" in detail["msg"]
    # Every breach the check found, not only the first (issue 21, defect 8).
    assert detail["ctx"]["details"] == {"segment": 0, "time_s": 2.5, **breaches}
    assert runs(robot_client, seed, booked) == []


def test_emergency_stop_reaches_the_worker_and_ends_the_run(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    booked = booked_session(robot_client, seed.headers())
    run = start(robot_client, seed, booked)
    response = robot_client.post("/api/v1/estop", headers=seed.headers())
    assert response.status_code == 200
    assert fake_worker.command_names()[-1] == "emergency_stop"
    # The answer comes first; the run's end and who pressed it are recorded right after.
    ended = wait_until(
        lambda: (
            (r := robot_client.get(f"/api/v1/runs/{run['id']}", headers=seed.headers()).json())["state"] == "ended"
            and r
        )
    )
    assert (ended["state"], ended["outcome"], ended["stopped_by_id"]) == ("ended", "emergency_stop", seed.therapist_id)
    estop = wait_until(lambda: [e for e in events(robot_client, seed, run["id"]) if e["kind"] == "emergency_stop"])
    assert estop[0]["user_id"] == seed.therapist_id and estop[0]["tick"] is not None
    assert robot_client.post("/api/v1/estop").status_code == 200  # logged out too (test_estop_policy)


def test_emergency_stop_does_not_wait_for_a_busy_database(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker, database: Database
) -> None:
    booked = booked_session(robot_client, seed.headers())
    start(robot_client, seed, booked)
    answers: list[int] = []
    # A long transaction holds the database (the test database serialises all access on one lock).
    with database.session():
        caller = threading.Thread(
            target=lambda: answers.append(robot_client.post("/api/v1/estop", headers=seed.headers()).status_code)
        )
        caller.start()
        assert fake_worker.estopped.wait(timeout=5.0), "the emergency stop waited for the database"
    caller.join(timeout=10.0)
    assert answers == [200]


def test_the_recorder_writes_telemetry_and_worker_events_and_ends_the_run_on_a_fall(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    booked = booked_session(robot_client, seed.headers())
    run = start(robot_client, seed, booked)
    fake_worker.produce(500)
    wait_until(lambda: robot_client.get(f"/api/v1/runs/{run['id']}", headers=seed.headers()).json()["sample_count"])
    fake_worker.produce(250)
    fake_worker.emit_event("fall", harness_load_n=310.0)
    ended = wait_until(
        lambda: (
            (r := robot_client.get(f"/api/v1/runs/{run['id']}", headers=seed.headers()).json())["state"] == "ended"
            and r
        )
    )
    assert ended["outcome"] == "fall"
    fall = [e for e in events(robot_client, seed, run["id"]) if e["kind"] == "fall"]
    assert fall[0]["detector"] == "test" and fall[0]["details"] == {"harness_load_n": 310.0}
    wait_until(
        lambda: robot_client.get(f"/api/v1/runs/{run['id']}", headers=seed.headers()).json()["sample_count"] == 750
    )


def test_the_telemetry_websocket_streams_frames(robot_client: TestClient, seed: Seed, fake_worker: FakeWorker) -> None:
    booked = booked_session(robot_client, seed.headers())
    run = start(robot_client, seed, booked)
    url = f"/api/v1/sessions/{booked.session_id}/telemetry"
    with robot_client.websocket_connect(url, headers=seed.headers()) as socket:
        fake_worker.produce(40)
        frame = wait_until(lambda: (f := json.loads(socket.receive_text()))["sample"] and f, timeout_s=5.0)
        assert (
            frame["type"] == "telemetry" and frame["run_id"] == run["id"] and frame["session_id"] == booked.session_id
        )
        assert frame["sample"]["tick"] == 39 and len(frame["sample"]["slider_position_m"]) == 12
        assert frame["state"]["state"] == "running"
    with pytest.raises(WebSocketDisconnect), robot_client.websocket_connect(url + "?token=forged") as socket:
        socket.receive_text()
    with (
        pytest.raises(WebSocketDisconnect),
        robot_client.websocket_connect("/api/v1/sessions/999999/telemetry", headers=seed.headers()) as socket,
    ):
        socket.receive_text()


def recorded_run(client: TestClient, seed: Seed, worker: FakeWorker, **patient: object) -> tuple[Booked, dict]:
    booked = booked_session(client, seed.headers(), **patient)
    run = start(client, seed, booked)
    worker.produce(300)
    worker.emit_event("limit_hit", limit="tilt_max_rad")
    worker.emit_event("controlled_stop", reason="limit")
    wait_until(lambda: client.get(f"/api/v1/runs/{run['id']}", headers=seed.headers()).json()["sample_count"] == 300)
    return booked, run


def test_a_run_exports_as_a_pseudonymised_self_describing_log(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    pytest.importorskip("server.exports")
    booked, run = recorded_run(robot_client, seed, fake_worker)
    response = robot_client.get(
        f"/api/v1/sessions/{booked.session_id}/export", params={"format": "json"}, headers=seed.headers()
    )
    assert response.status_code == 200, response.text
    assert "attachment" in response.headers["content-disposition"]
    assert PATIENT["name"] not in response.text and PATIENT["identifier"] not in response.text
    document = response.json()
    text = json.dumps(document)
    assert "P-" in text and "limit_hit" in text and f"run-{run['id']}" in text
    for fmt in ("csv", "parquet", "c3d"):
        exported = robot_client.get(
            f"/api/v1/sessions/{booked.session_id}/export", params={"format": fmt}, headers=seed.headers()
        )
        assert exported.status_code == 200 and len(exported.content) > 100, fmt
    identified = robot_client.get(
        f"/api/v1/sessions/{booked.session_id}/export",
        params={"format": "json", "identify": "true"},
        headers=seed.headers(),
    )
    assert identified.status_code == 403
    as_admin = robot_client.get(
        f"/api/v1/sessions/{booked.session_id}/export",
        params={"format": "json", "identify": "true"},
        headers=seed.headers("admin"),
    )
    assert PATIENT["name"] in as_admin.text
    exports = robot_client.get(
        "/api/v1/audit", params={"resource_type": "session_run"}, headers=seed.headers("admin")
    ).json()
    assert [e["details"]["format"] for e in exports if e["action"] == "export"][:2] == ["json", "c3d"]


def test_export_of_a_session_without_recording_is_refused(robot_client: TestClient, seed: Seed) -> None:
    pytest.importorskip("server.exports")
    booked = booked_session(robot_client, seed.headers())
    none_yet = robot_client.get(f"/api/v1/sessions/{booked.session_id}/export", headers=seed.headers())
    assert none_yet.status_code == 404
    start(robot_client, seed, booked)
    empty = robot_client.get(f"/api/v1/sessions/{booked.session_id}/export", headers=seed.headers())
    assert empty.status_code == 409 and "no recorded telemetry" in empty.json()["detail"]


def test_bulk_export_selects_runs_by_date_and_diagnosis(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    pytest.importorskip("server.exports")
    _, stroke_run = recorded_run(robot_client, seed, fake_worker)
    robot_client.post("/api/v1/estop", headers=seed.headers())  # frees the robot for the next patient
    acknowledged = robot_client.post(  # the limit stop is attended to before the robot starts again
        f"/api/v1/runs/{stroke_run['id']}/acknowledge", json={"note": "checked"}, headers=seed.headers()
    )
    assert acknowledged.status_code == 200, acknowledged.text
    import datetime as dt

    today = dt.datetime.now(dt.UTC).date()
    other = booked_session(
        robot_client, seed.headers(), identifier="MRN-PD", diagnosis="Parkinson", start="2031-05-06T10:00:00+00:00"
    )
    start(robot_client, seed, other)
    params = {"from_date": str(today), "to_date": str(today), "diagnosis": "Stroke"}
    response = robot_client.get("/api/v1/exports/bulk", params=params, headers=seed.headers())
    assert response.status_code == 200, response.text
    with zipfile.ZipFile(io.BytesIO(response.content)) as archive:
        index = json.loads(archive.read("index.json"))
        assert [s["session_id"] for s in index["sessions"]] == [f"run-{stroke_run['id']}"]
        assert index["selection"]["diagnosis"] == "Stroke"
        assert not any(PATIENT["name"] in archive.read(n).decode("latin-1") for n in archive.namelist())
    yesterday = str(today - dt.timedelta(days=1))
    nothing = robot_client.get(
        "/api/v1/exports/bulk", params={"from_date": yesterday, "to_date": yesterday}, headers=seed.headers()
    )
    assert nothing.status_code == 404
    backwards = robot_client.get(
        "/api/v1/exports/bulk", params={"from_date": str(today), "to_date": yesterday}, headers=seed.headers()
    )
    assert backwards.status_code == 422


@pytest.mark.parametrize(
    ("kind", "details", "outcome"),
    [
        ("fall", {}, "fall"),
        ("limit_hit", {"limit": "tilt"}, "limit_hit"),
        ("controlled_stop", {"reason": "operator"}, "stopped"),
        ("controlled_stop", {"reason": "watchdog"}, "interrupted"),  # the console went silent
        ("controlled_stop", {"reason": "service_lost"}, "interrupted"),
        ("controlled_stop", {"reason": "tracking_error"}, "fault"),
        ("prescription_completed", {}, "completed"),
        ("state", {"to": "paused"}, None),
    ],
)
def test_worker_events_decide_the_run_outcome(kind: str, details: dict, outcome: str | None) -> None:
    assert terminal_outcome_of(kind, details) == outcome


def test_a_completed_prescription_completes_the_booking(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    booked = booked_session(robot_client, seed.headers())
    run = start(robot_client, seed, booked)
    fake_worker.produce(100)
    fake_worker.emit_event("prescription_completed")
    fake_worker.emit_event("controlled_stop", reason="completed")
    wait_until(lambda: robot_client.get(f"/api/v1/runs/{run['id']}", headers=seed.headers()).json()["state"] == "ended")
    assert robot_client.get(f"/api/v1/runs/{run['id']}", headers=seed.headers()).json()["outcome"] == "completed"
    booking = robot_client.get(f"/api/v1/sessions/{booked.session_id}", headers=seed.headers()).json()
    assert booking["status"] == "completed"


def test_reset_of_a_robot_with_nothing_latched_is_a_409_not_a_500(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    from server.messages import CommandRefused

    fake_worker.refuse_with = CommandRefused("reset: refused in state idle")
    response = robot_client.post("/api/v1/robot/reset", headers=seed.headers())
    assert response.status_code == 409 and "idle" in response.json()["detail"]
    fake_worker.refuse_with = None
    assert robot_client.post("/api/v1/robot/reset", headers=seed.headers()).status_code == 200
    assert fake_worker.command_names()[-1] == "reset"
