"""After a run (issue 16): the acknowledgement a fall needs before the robot runs again (an event of the
run), the therapist's SOAP notes, and the PDF reports whose text (read back with pypdf) holds the run's facts."""

from __future__ import annotations

import io
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pypdf import PdfReader

from tests.server.conftest import FakeWorker, Seed, booked_session, wait_until

SOAP = {
    "subjective": "Reports mild dizziness after the second segment.",
    "objective": "Stepped once to the right at the fall.",
    "assessment": "Lateral control improving; fatigue late in the run.",
    "plan": "Shorter segments next week, same amplitude.",
}


def _pdf_text(response: Any) -> str:
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/pdf"
    return "\n".join(page.extract_text() for page in PdfReader(io.BytesIO(response.content)).pages)


def _fallen_run(client: TestClient, seed: Seed, worker: FakeWorker) -> dict[str, Any]:
    """A started run with 1.5 s of telemetry that a fall (harness load 310 N) ended."""
    booked = booked_session(client, seed.headers())
    started = client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers())
    assert started.status_code == 200, started.text
    run = started.json()
    worker.produce(1500)
    worker.emit_event("fall", harness_load_n=310.0)
    return wait_until(
        lambda: (
            (r := client.get(f"/api/v1/runs/{run['id']}", headers=seed.headers()).json())["state"] == "ended"
            and r["sample_count"] == 1500
            and r
        )
    )


def test_a_fall_needs_one_acknowledgement_recorded_as_an_event(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    run = _fallen_run(robot_client, seed, fake_worker)
    headers = seed.headers()
    pending = robot_client.get("/api/v1/reviews/pending", params={"robot": run["robot"]}, headers=headers).json()
    assert pending["run_id"] == run["id"] and pending["outcome"] == "fall" and pending["needs_acknowledgement"]
    assert (
        robot_client.get("/api/v1/reviews/pending", params={"robot": "another-robot"}, headers=headers).json() is None
    )

    answer = robot_client.post(
        f"/api/v1/runs/{run['id']}/acknowledge", json={"note": "patient checked"}, headers=headers
    )
    assert answer.status_code == 200, answer.text
    assert answer.json()["outcome"] == "fall" and answer.json()["user_id"] == seed.therapist_id
    events = robot_client.get(f"/api/v1/runs/{run['id']}/events", headers=headers).json()
    acknowledged = [e for e in events if e["kind"] == "acknowledged"]
    assert len(acknowledged) == 1 and acknowledged[0]["user_id"] == seed.therapist_id
    assert acknowledged[0]["details"] == {"outcome": "fall", "note": "patient checked"}
    assert robot_client.get("/api/v1/reviews/pending", params={"robot": run["robot"]}, headers=headers).json() is None

    again = robot_client.post(f"/api/v1/runs/{run['id']}/acknowledge", json={}, headers=headers)
    assert again.status_code == 409 and "already acknowledged" in again.json()["detail"]
    audit = robot_client.get("/api/v1/audit", params={"resource_type": "session_run"}, headers=seed.headers("admin"))
    assert any(entry["action"] == "acknowledge" for entry in audit.json())


def test_only_falls_faults_and_limit_stops_are_acknowledged(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    booked = booked_session(robot_client, seed.headers())
    run = robot_client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers()).json()
    refused = robot_client.post(f"/api/v1/runs/{run['id']}/acknowledge", json={}, headers=seed.headers())
    assert refused.status_code == 409 and "nothing to acknowledge" in refused.json()["detail"]
    review = robot_client.get(f"/api/v1/runs/{run['id']}/review", headers=seed.headers()).json()
    assert review["needs_acknowledgement"] is False and review["acknowledgement"] is None


def test_soap_notes_are_kept_per_run_and_audited(robot_client: TestClient, seed: Seed, fake_worker: FakeWorker) -> None:
    run = _fallen_run(robot_client, seed, fake_worker)
    saved = robot_client.put(f"/api/v1/runs/{run['id']}/notes", json=SOAP, headers=seed.headers())
    assert saved.status_code == 200, saved.text
    notes = robot_client.get(f"/api/v1/runs/{run['id']}/review", headers=seed.headers()).json()["notes"]
    assert {key: notes[key] for key in SOAP} == SOAP and notes["author_id"] == seed.therapist_id
    too_long = robot_client.put(f"/api/v1/runs/{run['id']}/notes", json={"plan": "x" * 10_001}, headers=seed.headers())
    assert too_long.status_code == 422 and too_long.json()["detail"][0]["loc"] == ["body", "plan"]
    notes = robot_client.get(f"/api/v1/runs/{run['id']}/review", headers=seed.headers()).json()["notes"]
    assert notes["plan"] == SOAP["plan"]  # nothing half-written


def test_run_report_pdf_holds_the_runs_facts(robot_client: TestClient, seed: Seed, fake_worker: FakeWorker) -> None:
    run = _fallen_run(robot_client, seed, fake_worker)
    robot_client.put(f"/api/v1/runs/{run['id']}/notes", json=SOAP, headers=seed.headers())
    robot_client.post(f"/api/v1/runs/{run['id']}/acknowledge", json={"note": "patient checked"}, headers=seed.headers())
    text = _pdf_text(robot_client.get(f"/api/v1/runs/{run['id']}/report.pdf", headers=seed.headers()))
    flat = " ".join(text.split())
    for fact in (
        f"Session report: run {run['id']}", "Greta Testperson", "MRN-4711", "165 cm", "60.0 kg",
        "Lateral sway, version 1", "sine", "amplitude 0.50 m/s²", "frequency 0.50 Hz", "30 s",
        "fall detected", "harness load 310 N", "1.5 s into the run",
        # 1.5 s of telemetry: too short for sway measures, and the report says so (issue 22 §6).
        "Not measured: the sway measures need at least 20 s of the run in motion", "Cue quality", "Perception error",
        SOAP["subjective"], SOAP["plan"], "patient checked", "Acknowledged by therapist at",
        "Therapist notes (SOAP), by therapist",
    ):  # fmt: skip
        assert fact in flat, f"{fact!r} is not in the report: {flat[:3000]}"
    assert robot_client.get("/api/v1/runs/999999/report.pdf", headers=seed.headers()).status_code == 404
    assert robot_client.get(f"/api/v1/runs/{run['id']}/report.pdf").status_code == 401


def test_progress_report_lists_runs_by_date_with_faulted_runs_marked(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    run = _fallen_run(robot_client, seed, fake_worker)
    patient_id = robot_client.get(f"/api/v1/sessions/{run['scheduled_session_id']}", headers=seed.headers()).json()[
        "patient_id"
    ]
    day = run["started_at"][:10]
    response = robot_client.get(
        f"/api/v1/patients/{patient_id}/progress.pdf", params={"from": day, "to": day}, headers=seed.headers()
    )
    flat = " ".join(_pdf_text(response).split())
    assert "Progress report: Greta Testperson (MRN-4711)" in flat
    assert f"Runs from {day} to {day}: 1." in flat and "✕ fall detected" in flat and "Lateral sway v1" in flat
    wrong_way = robot_client.get(
        f"/api/v1/patients/{patient_id}/progress.pdf", params={"from": day, "to": "2000-01-01"}, headers=seed.headers()
    )
    assert wrong_way.status_code == 422 and wrong_way.json()["detail"][0]["loc"] == ["body", "to"]


@pytest.mark.parametrize("query", ["jurgen", "JÜRGEN", "Jürgen", "sorensen", "aebi"])
def test_search_ignores_accents_and_case(client: TestClient, seed: Seed, query: str) -> None:
    from tests.server.conftest import create_patient

    headers = seed.headers()
    wanted = {create_patient(client, headers, identifier="MRN-J1", name="Jürgen Sørensen"),
              create_patient(client, headers, identifier="MRN-J2", name="Jürgen Æbischer")}  # fmt: skip
    create_patient(client, headers, identifier="MRN-J3", name="Greta Testperson")
    found = {p["id"] for p in client.get("/api/v1/patients", params={"search": query}, headers=headers).json()}
    expected = {"sorensen": 1, "aebi": 1}.get(query, 2)
    assert len(found) == expected and found <= wanted


def test_search_treats_like_wildcards_literally(client: TestClient, seed: Seed) -> None:
    from tests.server.conftest import create_patient

    create_patient(client, seed.headers(), identifier="MRN-W1", name="Anna Muster")
    assert client.get("/api/v1/patients", params={"search": "%"}, headers=seed.headers()).json() == []
    assert client.get("/api/v1/patients", params={"search": "_nna"}, headers=seed.headers()).json() == []


def test_archived_patients_leave_the_lists_and_come_back(client: TestClient, seed: Seed) -> None:
    from tests.server.conftest import create_patient

    headers = seed.headers()
    patient_id = create_patient(client, headers, notes="uses a cane outdoors")
    archived = client.patch(
        f"/api/v1/patients/{patient_id}", json={"archived": True}, headers={**headers, "If-Match": '"1"'}
    )
    assert archived.status_code == 200 and archived.json()["archived_at"] is not None
    assert client.get("/api/v1/patients", headers=headers).json() == []
    listed = client.get("/api/v1/patients", params={"include_archived": True}, headers=headers).json()
    assert [p["id"] for p in listed] == [patient_id] and listed[0]["notes"] == "uses a cane outdoors"
    restored = client.patch(
        f"/api/v1/patients/{patient_id}", json={"archived": False}, headers={**headers, "If-Match": '"2"'}
    )
    assert restored.json()["archived_at"] is None
    assert [p["id"] for p in client.get("/api/v1/patients", headers=headers).json()] == [patient_id]
    entries = client.get(
        "/api/v1/audit", params={"resource_type": "patient", "resource_id": patient_id}, headers=seed.headers("admin")
    ).json()
    actions = [entry["action"] for entry in entries]
    assert "archive" in actions and "restore" in actions


def test_a_patient_without_sex_is_refused(client: TestClient, seed: Seed) -> None:
    from tests.server.conftest import PATIENT

    body = {key: value for key, value in PATIENT.items() if key != "sex"}
    response = client.post("/api/v1/patients", json=body, headers=seed.headers())
    assert response.status_code == 422 and response.json()["detail"][0]["loc"] == ["body", "sex"]


def test_the_robot_does_not_start_again_before_the_fall_is_acknowledged(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    run = _fallen_run(robot_client, seed, fake_worker)
    booking = robot_client.get(f"/api/v1/sessions/{run['scheduled_session_id']}", headers=seed.headers()).json()
    commands_before = fake_worker.command_names()
    refused = robot_client.post(f"/api/v1/sessions/{booking['id']}/start", headers=seed.headers())
    assert refused.status_code == 409, refused.text
    assert refused.json()["field"] == "acknowledgement" and f"run {run['id']}" in refused.json()["detail"]
    assert fake_worker.command_names() == commands_before  # nothing was sent to the robot
    runs = robot_client.get(f"/api/v1/sessions/{booking['id']}/runs", headers=seed.headers()).json()
    assert [r["id"] for r in runs] == [run["id"]]  # nothing was written
    robot_client.post(f"/api/v1/runs/{run['id']}/acknowledge", json={}, headers=seed.headers())
    started = robot_client.post(f"/api/v1/sessions/{booking['id']}/start", headers=seed.headers())
    assert started.status_code == 200, started.text
    assert fake_worker.command_names()[len(commands_before) :] == ["load_plan", "start_motion"]


def test_cue_quality_is_near_zero_when_the_platform_delivers_the_cue_and_grows_when_it_does_not() -> None:
    """A platform swaying x = A sin(ωt) delivers a specific force −Aω² sin(ωt) (no tilt): commanded that
    way, the perceived error is a small fraction of the cue; commanded twice as strong, it is not."""
    import numpy as np

    from server.reports.facts import cue_quality

    rate_hz, amplitude_m, omega = 250.0, 0.02, 2 * np.pi * 0.5
    time_s = np.arange(0, 20, 1 / rate_hz)
    pose = np.zeros((len(time_s), 6))
    pose[:, 0] = amplitude_m * np.sin(omega * time_s)
    delivered = np.zeros((len(time_s), 3))
    delivered[:, 0] = -amplitude_m * omega**2 * np.sin(omega * time_s)
    columns = {"time_s": time_s, "stance_pose": pose, "measured_stance_pose": pose,
               "cue_angular_velocity_rad_s": np.zeros((len(time_s), 3))}  # fmt: skip
    matched = cue_quality({**columns, "cue_specific_force_m_s2": delivered})
    doubled = cue_quality({**columns, "cue_specific_force_m_s2": 2 * delivered})
    assert matched is not None and doubled is not None
    cue_rms = matched["cue_rms_m_s2"]["x"]
    assert matched["perceived_error_rms_m_s2"]["x"] < 0.05 * cue_rms
    assert matched["correlation"]["x"] > 0.999 and matched["correlation"]["y"] is None  # no y motion
    assert doubled["perceived_error_rms_m_s2"]["x"] > 10 * matched["perceived_error_rms_m_s2"]["x"]
    assert doubled["perception_error_thresholds"] > matched["perception_error_thresholds"]


def test_the_delivered_cue_is_the_measured_motion_not_the_jitter_of_the_time_stamps() -> None:
    """Issue 22 §6: the run PDF showed the platform's delivered sideways acceleration swinging ±100 m/s² against a
    commanded 0.3–0.5 m/s² (correlation 0.01): the commanded pose, differentiated twice over time stamps that
    jitter by tenths of a millisecond. A 1 kHz run whose stamps jitter so, swaying y = A sin(ωt): what the
    platform delivered is −Aω² sin(ωt), within a few per cent, and it follows the cue."""
    import numpy as np

    from server.reports.facts import cue_quality

    rate_hz, amplitude_m, omega = 1000.0, 0.02, 2 * np.pi * 0.5
    nominal = np.arange(0, 20, 1 / rate_hz)
    stamps = nominal + np.random.default_rng(7).uniform(0.0, 4e-4, len(nominal))  # when each tick ran
    commanded = np.zeros((len(nominal), 6))
    commanded[:, 1] = amplitude_m * np.sin(omega * nominal)  # the plan's samples, on the period grid
    measured = np.zeros((len(nominal), 6))
    measured[:, 1] = amplitude_m * np.sin(omega * stamps)  # where the platform was when it was read
    cue = np.zeros((len(nominal), 3))
    cue[:, 1] = -amplitude_m * omega**2 * np.sin(omega * nominal)
    columns = {"time_s": stamps, "stance_pose": commanded, "measured_stance_pose": measured,
               "cue_specific_force_m_s2": cue, "cue_angular_velocity_rad_s": np.zeros((len(nominal), 3))}  # fmt: skip
    quality = cue_quality(columns)
    assert quality is not None
    delivered = quality["delivered_m_s2"][1][200:-200]  # y, away from the ends
    peak = amplitude_m * omega**2  # 0.197 m/s²
    assert np.max(np.abs(delivered)) == pytest.approx(peak, rel=0.05), np.max(np.abs(delivered))
    assert quality["correlation"]["y"] > 0.99
