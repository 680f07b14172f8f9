"""Issue 20, defect 12 / build 9: every stop that moved the patient (emergency stop, watchdog, fault, fall,
limit stop) needs an acknowledgement before the robot starts again; the therapist's own stop and a
completed run do not."""

from __future__ import annotations

from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.server.conftest import FakeWorker, Seed, booked_session, wait_until


def _ended_run(client: TestClient, seed: Seed, worker: FakeWorker, end: Any) -> tuple[dict[str, Any], int]:
    """A run that `end(client, worker)` ended, and the booking to start next."""
    booked = booked_session(client, seed.headers())
    started = client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers())
    assert started.status_code == 200, started.text
    run = started.json()
    worker.produce(200)
    end(client, seed, run)
    ended = wait_until(
        lambda: (r := client.get(f"/api/v1/runs/{run['id']}", headers=seed.headers()).json())["state"] == "ended" and r
    )
    return ended, booked.session_id


def _emergency_stop(client: TestClient, seed: Seed, run: dict[str, Any]) -> None:
    assert client.post("/api/v1/estop").status_code == 200


def _worker_event(kind: str, **details: Any) -> Any:
    def end(client: TestClient, seed: Seed, run: dict[str, Any]) -> None:
        client.app.state.robot.daemon.worker.emit_event(kind, **details)

    return end


def _operator_stop(client: TestClient, seed: Seed, run: dict[str, Any]) -> None:
    stopped = client.post(f"/api/v1/sessions/{run['scheduled_session_id']}/stop", headers=seed.headers())
    assert stopped.status_code == 200, stopped.text


MOVING_STOPS = {
    "emergency stop": (_emergency_stop, "emergency_stop"),
    "watchdog": (_worker_event("controlled_stop", reason="watchdog"), "interrupted"),
    "fault": (_worker_event("fault", reason="hal_fault"), "fault"),
    "fall": (_worker_event("fall", harness_load_n=310.0), "fall"),
    "limit stop": (_worker_event("limit_hit", limit="tilt_max_rad"), "limit_hit"),
}


@pytest.mark.parametrize("stop", list(MOVING_STOPS))
def test_every_stop_that_moved_the_patient_needs_an_acknowledgement_before_the_next_start(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker, stop: str
) -> None:
    end, outcome = MOVING_STOPS[stop]
    run, session_id = _ended_run(robot_client, seed, fake_worker, end)
    assert run["outcome"] == outcome, run
    assert robot_client.post("/api/v1/robot/reset", headers=seed.headers()).status_code == 200
    commands_before = fake_worker.command_names()
    refused = robot_client.post(f"/api/v1/sessions/{session_id}/start", headers=seed.headers())
    assert refused.status_code == 409, f"the robot started again after a {stop} nobody acknowledged: {refused.text}"
    detail = refused.json()["detail"]
    assert refused.json()["field"] == "acknowledgement", refused.text
    assert f"run {run['id']}" in detail and f"/runs/{run['id']}/acknowledge" in detail, detail
    assert fake_worker.command_names() == commands_before  # nothing was sent to the robot
    pending = robot_client.get("/api/v1/reviews/pending", params={"robot": run["robot"]}, headers=seed.headers())
    assert pending.json() is not None and pending.json()["run_id"] == run["id"], pending.text

    acknowledged = robot_client.post(
        f"/api/v1/runs/{run['id']}/acknowledge", json={"note": "patient attended to"}, headers=seed.headers()
    )
    assert acknowledged.status_code == 200, acknowledged.text
    assert acknowledged.json()["outcome"] == outcome
    started = robot_client.post(f"/api/v1/sessions/{session_id}/start", headers=seed.headers())
    assert started.status_code == 200, started.text


def test_the_refusal_names_the_emergency_stop(robot_client: TestClient, seed: Seed, fake_worker: FakeWorker) -> None:
    _, session_id = _ended_run(robot_client, seed, fake_worker, _emergency_stop)
    refused = robot_client.post(f"/api/v1/sessions/{session_id}/start", headers=seed.headers())
    assert refused.status_code == 409 and "emergency stop that is not acknowledged" in refused.json()["detail"]


@pytest.mark.parametrize(
    "end", [_operator_stop, _worker_event("prescription_completed")], ids=["operator stop", "completed"]
)
def test_the_therapists_own_stop_and_a_completed_run_need_no_acknowledgement(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker, end: Any
) -> None:
    run, session_id = _ended_run(robot_client, seed, fake_worker, end)
    assert run["outcome"] in ("stopped", "completed"), run
    refused = robot_client.post(f"/api/v1/runs/{run['id']}/acknowledge", json={}, headers=seed.headers())
    assert refused.status_code == 409 and "nothing to acknowledge" in refused.json()["detail"], refused.text
    if run["outcome"] == "completed":  # the booking is done: start the patient's next one
        session_id = booked_session(
            robot_client, seed.headers(), identifier="MRN-NEXT", start="2031-05-06T12:00:00+00:00"
        ).session_id
    started = robot_client.post(f"/api/v1/sessions/{session_id}/start", headers=seed.headers())
    assert started.status_code == 200, started.text


def test_a_reset_pressed_while_the_robot_still_brakes_waits_for_the_drives_to_be_off(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    """CI failure, 2026-12-07: Reset clicked within the emergency stop's ramp (at most 2 s) was refused ("the stop
    ramp is still running") and the robot stayed latched; a clinician presses Reset once. The daemon now waits
    for the ramp and resets then; any other refusal still answers at once."""
    fake_worker.braking_resets = 3  # the worker refuses three resets while it brakes, then takes one
    answer = robot_client.post("/api/v1/robot/reset", headers=seed.headers())
    assert answer.status_code == 200, answer.text
    assert fake_worker.command_names().count("reset") == 1 and fake_worker.braking_resets == 0
    fake_worker.refuse_with = RuntimeError("reset: not accepted in state idle")
    refused = robot_client.post("/api/v1/robot/reset", headers=seed.headers())
    assert refused.status_code == 409 and "state idle" in refused.json()["detail"], refused.text
