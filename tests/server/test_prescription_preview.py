"""Preview jobs (`POST /prescriptions/previews`, `GET /prescriptions/previews/{id}`: the editor's motion
preview), `GET /patients/{id}/balance` (the profile's trend) and `GET /viz` without a 3D view."""

from __future__ import annotations

import stat
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from core.plan.prescription import PrescriptionBody
from core.robot import default_twin
from server.app import create_app
from server.db import Database
from server.prescriptions.preview import prescription_preview
from server.prescriptions.preview_jobs import PREVIEW_JOBS_DIRECTORY
from server.sessions.balance import foot_origins_m, run_balance
from server.settings import Settings
from tests.server.conftest import Seed, create_patient, finished_preview, run_columns

TWIN = default_twin()
SINE = {"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.5}, "duration_s": 6.0}


def _preview(segments: list[dict], control_rate_hz: int = 250, cueing: str = "classical") -> dict:
    prescription = PrescriptionBody.model_validate({"segments": segments, "cueing": cueing})
    return prescription_preview(prescription, TWIN, control_rate_hz=control_rate_hz)


def test_preview_shows_the_chosen_algorithm_perceived_at_the_head() -> None:
    """Issue 14: the editor's preview compares the perceived cue and what the platform delivers at the head."""
    errors = {}
    for cueing in ("classical", "optimal"):
        preview = _preview([SINE], cueing=cueing)
        assert preview["cueing"] == cueing and preview["head_height_m"] == 1.6
        assert preview["verdict"]["accepted"] is True
        cue = np.array(preview["perceived_cue_m_s2"], dtype=float)
        delivered = np.array(preview["perceived_platform_m_s2"], dtype=float)
        assert cue.shape == delivered.shape == (3, len(preview["time_s"]))
        assert len(preview["perceived_platform_rate_rad_s"]) == 3
        errors[cueing] = float(np.sqrt(np.mean((delivered - cue) ** 2)))
    assert errors["optimal"] < 0.5 * errors["classical"]


def test_preview_of_a_lateral_sine_moves_the_platform_sideways_within_the_stroke() -> None:
    preview = _preview([SINE])
    assert preview["verdict"]["accepted"] is True
    n = len(preview["time_s"])
    assert all(len(column) == n for key in ("platform_position_m", "perceived_cue_m_s2", "slider_position_m")
               for column in preview[key])  # fmt: skip
    lateral = np.array(preview["platform_position_m"][1], dtype=float)
    forward = np.array(preview["platform_position_m"][0], dtype=float)
    assert np.max(np.abs(lateral)) > 0.005 and np.max(np.abs(forward)) < 1e-6
    perceived_cue_y = np.array(preview["perceived_cue_m_s2"][1], dtype=float)
    assert np.max(np.abs(perceived_cue_y)) > 0.05
    sliders = np.array(preview["slider_position_m"], dtype=float)
    assert np.all(sliders >= np.array(preview["stroke_min_m"])[:, None])
    assert np.all(sliders <= np.array(preview["stroke_max_m"])[:, None])
    # The timeline includes the fade out and the return to neutral after the segment.
    assert preview["duration_s"] > SINE["duration_s"]


def test_preview_reports_the_limit_the_robot_would_refuse() -> None:
    tight = {**SINE, "cue": {**SINE["cue"], "amplitude_m_s2": 2.0}, "limits": {"tilt_max_rad": 0.005}}
    preview = _preview([tight])
    assert preview["verdict"]["accepted"] is False
    assert preview["verdict"]["rejection"]["limit"] == "tilt"
    assert preview["verdict"]["rejection"]["segment"] == 0


PREVIEWS = "/api/v1/prescriptions/previews"
# Eight classical segments, 488 s in all: its plots' curves alone take seconds, each step reported.
LONG = [{**SINE, "duration_s": 60.0}] * 8


def reader(client: TestClient, headers: dict[str, str]) -> Callable[[str], Any]:
    """A GET under /api/v1 as the user with `headers`."""
    return lambda path: client.get(f"/api/v1{path}", headers=headers)


def job_files(settings: Settings) -> list[str]:
    return sorted(path.name for path in (settings.data_dir / PREVIEW_JOBS_DIRECTORY).glob("*.json"))


def test_preview_api_names_the_invalid_field_and_starts_no_job(
    client: TestClient, seed: Seed, settings: Settings
) -> None:
    bad = {**SINE, "cue": {**SINE["cue"], "frequency_hz": -1.0}}
    response = client.post(PREVIEWS, json={"segments": [SINE, bad]}, headers=seed.headers())
    assert response.status_code == 422
    locations = [".".join(map(str, item["loc"])) for item in response.json()["detail"]]
    assert any("segments[1].cue.frequency_hz" in loc or "segments.1.cue.frequency_hz" in loc for loc in locations)
    too_long = client.post(PREVIEWS, json={"segments": [{**SINE, "duration_s": 400.0}] * 2}, headers=seed.headers())
    assert too_long.status_code == 422, too_long.text
    [item] = too_long.json()["detail"]
    assert item["loc"] == ["body", "segments"] and item["input"] == "802 s in all"
    assert item["ctx"]["limit"] == "the preview covers at most 600 s"
    assert job_files(settings) == []


def test_preview_api_answers_with_plot_data(client: TestClient, seed: Seed) -> None:
    patient_id = create_patient(client, seed.headers())
    started = client.post(PREVIEWS, json={"segments": [SINE], "patient_id": patient_id}, headers=seed.headers())
    assert started.status_code == 202, started.text
    assert started.json() == {"preview_id": started.json()["preview_id"], "state": "planning", "progress": 0.0}
    job = finished_preview(reader(client, seed.headers()), started)
    assert job["state"] == "ready" and job["progress"] == 1.0 and job["refusal"] is None, job
    assert job["preview"]["verdict"]["accepted"] is True and len(job["preview"]["time_s"]) > 100


def test_a_preview_job_answers_at_once_and_reports_its_progress(client: TestClient, seed: Seed) -> None:
    """Issue 21 defect 6: the request no longer waits for the work; the job says how far it is."""
    started = client.post(PREVIEWS, json={"segments": LONG}, headers=seed.headers())
    assert started.status_code == 202, started.text
    # Seen before any planning could be done: the preview process alone takes seconds to start.
    first = client.get(started.headers["location"], headers=seed.headers()).json()
    assert first["state"] == "planning" and first["progress"] < 1.0 and first["preview"] is None, first
    seen: list[dict[str, Any]] = []
    job = finished_preview(reader(client, seed.headers()), started, seen=seen)
    assert job["state"] == "ready" and job["progress"] == 1.0, job
    assert job["preview"]["duration_s"] > 480.0
    progress = [answer["progress"] for answer in seen]
    assert progress == sorted(progress), progress
    assert any(0.0 < fraction < 1.0 for fraction in progress), progress


def test_a_preview_job_is_only_its_owners(client: TestClient, seed: Seed) -> None:
    """As export jobs: another therapist, and the admin too, get 404 (a job holds a patient's prescription)."""
    started = client.post(PREVIEWS, json={"segments": [SINE]}, headers=seed.headers())
    location = started.headers["location"]
    for other in ("colleague", "admin"):
        assert client.get(location, headers=seed.headers(other)).status_code == 404
    assert client.get(location).status_code == 401
    assert client.get(f"{PREVIEWS}/{'0' * 32}", headers=seed.headers()).status_code == 404
    assert finished_preview(reader(client, seed.headers()), started)["state"] == "ready"
    assert client.get(location, headers=seed.headers("colleague")).status_code == 404


def test_another_web_process_answers_the_poll(
    client: TestClient, seed: Seed, settings: Settings, database: Database
) -> None:
    """`serve --workers 2`: the poll may reach another web process than the one that started the job; a second
    app on the same data directory stands in for it."""
    started = client.post(PREVIEWS, json={"segments": [SINE]}, headers=seed.headers())
    with TestClient(create_app(settings, database=database, worker=None)) as other_process:
        job = finished_preview(reader(other_process, seed.headers()), started)
        assert job["state"] == "ready" and job["preview"]["verdict"]["accepted"] is True, job
        colleague = other_process.get(started.headers["location"], headers=seed.headers("colleague"))
        assert colleague.status_code == 404


def test_a_prescription_the_planner_refuses_ends_the_job_refused(
    client: TestClient, seed: Seed, settings: Settings
) -> None:
    """A refusal found while planning (a segment shorter than its soft start) reads as the API's 422 items."""
    started = client.post(PREVIEWS, json={"segments": [SINE, {**SINE, "duration_s": 0.5}]}, headers=seed.headers())
    job = finished_preview(reader(client, seed.headers()), started)
    assert job["state"] == "refused" and job["preview"] is None, job
    [item] = job["refusal"]
    assert item["loc"] == ["body", "segments[1]", "duration_s"] and item["input"] == 0.5, item
    assert item["ctx"]["limit"] == "must be at least the soft start, 1 s" and item["type"] == "value_error"
    assert item["msg"] == "segments[1].duration_s = 0.5: must be at least the soft start, 1 s"
    assert [name.removesuffix(".json") for name in job_files(settings)] == [job["preview_id"]]
    directory = settings.data_dir / PREVIEW_JOBS_DIRECTORY
    assert stat.S_IMODE(directory.stat().st_mode) == 0o700  # a job holds a patient's prescription
    assert stat.S_IMODE((directory / f"{job['preview_id']}.json").stat().st_mode) == 0o600


def test_preview_needs_a_login(client: TestClient) -> None:
    assert client.post(PREVIEWS, json={"segments": [SINE]}).status_code == 401


def test_balance_of_a_run_is_the_sway_of_the_net_centre_of_pressure() -> None:
    n = 2500  # 25 s: longer than the shortest window measured (20 s)
    time_s = np.arange(n) / 100.0
    forces = np.full((n, 2), 300.0)
    cops = np.zeros((n, 2, 2))
    cops[:, :, 0] = 0.01 * np.sin(2 * np.pi * 0.5 * time_s)[:, None]  # both feet sway 10 mm AP
    metrics = run_balance(run_columns(time_s, forces, cops), TWIN)
    assert metrics is not None
    assert metrics["range_ap_m"] == pytest.approx(0.02, rel=1e-3)
    assert metrics["range_ml_m"] == pytest.approx(0.0, abs=1e-12)  # equal loads: the feet's offsets cancel
    np.testing.assert_allclose(foot_origins_m(TWIN).sum(axis=0), 0.0)


def test_balance_needs_a_loaded_plate() -> None:
    time_s = np.arange(0.0, 30.0, 0.01)
    assert run_balance(run_columns(time_s, np.zeros((len(time_s), 2)), np.zeros((len(time_s), 2, 2))), TWIN) is None


def test_balance_trend_of_a_patient_without_runs_is_empty(client: TestClient, seed: Seed) -> None:
    patient_id = create_patient(client, seed.headers())
    response = client.get(f"/api/v1/patients/{patient_id}/balance", headers=seed.headers())
    assert response.status_code == 200 and response.json() == []
    assert client.get("/api/v1/patients/999999/balance", headers=seed.headers()).status_code == 404


def test_viz_status_without_a_view(client: TestClient, seed: Seed) -> None:
    response = client.get("/api/v1/viz", headers=seed.headers())
    assert response.status_code == 200 and response.json()["available"] is False
    # The admin: a therapist is first asked whether the run is in their care (404 for an unknown one).
    assert client.post("/api/v1/viz/replay", json={"run_id": 1}, headers=seed.headers("admin")).status_code == 503
    assert client.get("/api/v1/viz").status_code == 401
