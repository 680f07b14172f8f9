"""Plans ahead, stored (issue 21, build 1): a booking's plan is built when it is booked, shown in words on
the booking, stored once by its key, and Start plays the stored plan instead of planning while the patient
waits; a plan whose inputs changed is made again, never played."""

from __future__ import annotations

import json
import pickle
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient
from typer.testing import CliRunner

from server.cli.main import app
from server.robotd.plan_store import PlanStore, StoredMotion
from tests.server.conftest import FakeWorker, Seed, book, booked_session, wait_until

SWAY: dict[str, Any] = {
    "cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.4, "frequency_hz": 0.5},
    "duration_s": 4.0,
}


def _plan(client: TestClient, seed: Seed, session_id: int) -> dict[str, Any]:
    response = client.get(f"/api/v1/sessions/{session_id}", headers=seed.headers())
    assert response.status_code == 200, response.text
    plan: dict[str, Any] = response.json()["plan"]
    return plan


def _ready(client: TestClient, seed: Seed, session_id: int) -> dict[str, Any]:
    return wait_until(
        lambda: (plan := _plan(client, seed, session_id))["state"] in ("ready", "refused") and plan, 120.0
    )


def test_a_booking_is_planned_ahead_and_start_plays_the_stored_plan(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    booked = booked_session(robot_client, seed.headers())
    planner = robot_client.app.state.robot.daemon.planner  # type: ignore[attr-defined]
    plan = _ready(robot_client, seed, booked.session_id)
    assert plan["state"] == "ready" and plan["progress"] == 1.0 and plan["reason"] is None
    assert len(plan["plan_id"]) == 24
    plans_before = planner.planned
    response = robot_client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers())
    assert response.status_code == 200, response.text
    assert planner.planned == plans_before, "Start planned again instead of playing the stored plan"
    (name, (loaded, report)) = fake_worker.calls[0]
    assert name == "load_plan" and isinstance(loaded.motion, StoredMotion)
    assert report["samples"] == loaded.played.samples
    # The worker maps the stored file: what crosses its pipe is the plan's directory, not its samples.
    assert len(pickle.dumps(loaded.motion)) < 1000 and loaded.played.samples > 10_000


def test_the_same_prescription_and_patient_share_one_plan_and_a_new_mass_makes_it_stale(
    robot_client: TestClient, seed: Seed
) -> None:
    headers = seed.headers()
    booked = booked_session(robot_client, headers)
    first = _ready(robot_client, seed, booked.session_id)
    second = book(
        robot_client,
        headers,
        patient_id=booked.patient_id,
        prescription_id=booked.prescription_id,
        start="2031-05-07T09:00:00+00:00",
    ).json()[0]
    assert second["plan"]["state"] == "ready" and second["plan"]["plan_id"] == first["plan_id"]
    patient = robot_client.get(f"/api/v1/patients/{booked.patient_id}", headers=headers).json()
    changed = robot_client.patch(
        f"/api/v1/patients/{booked.patient_id}",
        json={"body_mass_kg": 95.0, "expected_version": patient["version"]},
        headers=headers,
    )
    assert changed.status_code == 200, changed.text
    stale = _plan(robot_client, seed, booked.session_id)
    assert stale["state"] == "stale" and stale["plan_id"] is None  # the old plan is never offered again
    remade = _ready(robot_client, seed, booked.session_id)
    assert remade["state"] == "ready" and remade["plan_id"] != first["plan_id"]


def test_a_plan_the_check_refuses_says_why_on_the_booking(robot_client: TestClient, seed: Seed) -> None:
    headers = seed.headers()
    booked = booked_session(robot_client, headers)
    too_fast = {
        "patient_id": booked.patient_id,
        "name": "Too fast",
        "segments": [
            {
                "cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 1.5, "frequency_hz": 1.0},
                "duration_s": 4.0,
                "limits": {"slider_velocity_max_m_s": 0.02},
            }
        ],
    }
    prescription = robot_client.post("/api/v1/prescriptions", json=too_fast, headers=headers)
    assert prescription.status_code == 201, prescription.text
    refused_booking = book(
        robot_client,
        headers,
        patient_id=booked.patient_id,
        prescription_id=prescription.json()["id"],
        start="2031-05-08T09:00:00+00:00",
    ).json()[0]
    plan = _ready(robot_client, seed, refused_booking["id"])
    assert plan["state"] == "refused" and "slider velocity" in plan["reason"] and "segment 0" in plan["reason"]


def test_the_plan_command_prints_the_plan_id_timings_and_report_and_stores_it(tmp_path: Path) -> None:
    prescription = tmp_path / "sway.json"
    prescription.write_text(json.dumps({"segments": [SWAY]}))
    outcome = CliRunner().invoke(app, ["plan", str(prescription), "--json", "--data-dir", str(tmp_path / "data")])
    assert outcome.exit_code == 0, outcome.output
    result = json.loads(outcome.output)
    assert result["feasible"] is True and result["rejected"] is None
    assert result["duration_s"] == result["report"]["duration_s"] > 4.0
    assert result["planning_wall_s"] > 0.0 and result["planning_cpu_s"] > 0.0
    plan, report = PlanStore(tmp_path / "data" / "plans").load(result["plan_id"])
    assert report == result["report"] and plan.played.samples == report["samples"]


def test_the_plan_command_refuses_naming_the_limit(tmp_path: Path) -> None:
    prescription = tmp_path / "fast.json"
    fast = {**SWAY, "cue": {**SWAY["cue"], "amplitude_m_s2": 1.5, "frequency_hz": 1.0}}
    prescription.write_text(json.dumps({"segments": [{**fast, "limits": {"slider_velocity_max_m_s": 0.02}}]}))
    outcome = CliRunner().invoke(app, ["plan", str(prescription), "--json"])
    assert outcome.exit_code == 1
    result = json.loads(outcome.output)
    assert result["feasible"] is False and result["rejected"]["limit"] == "slider_velocity"


def test_the_store_keeps_to_its_size_removing_the_least_recently_used_plan(tmp_path: Path, twin: Any) -> None:
    import os

    from server.realtime.supervisor import SupervisorConfig
    from server.robotd.planner import checked_plan

    config = SupervisorConfig()
    plans = [checked_plan(twin, 250, config, {"segments": [{**SWAY, "duration_s": d}]}, None) for d in (4, 5)]
    unbounded = PlanStore(tmp_path / "plans")
    unbounded.save("a", *plans[0])
    size = sum(item.stat().st_size for item in unbounded.path("a").iterdir())
    store = PlanStore(tmp_path / "plans", max_bytes=int(size * 1.5))
    os.utime(store.path("a"), (1.0, 1.0))  # long unused
    store.save("b", *plans[1])
    assert not store.has("a") and store.has("b")  # "a" went to make room; the new plan stays
    plan, report = store.load("b")
    assert plan.played.samples == report["samples"]
