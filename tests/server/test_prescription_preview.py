"""`POST /prescriptions/preview` (the editor's motion preview), `GET /patients/{id}/balance` (the profile's
trend) and `GET /viz` without a 3D view."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from core.plan.prescription import PrescriptionBody
from core.robot import default_twin
from server.prescriptions.preview import prescription_preview
from server.sessions.balance import foot_origins_m, run_balance
from tests.server.conftest import Seed, create_patient

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


def test_preview_api_names_the_invalid_field(client: TestClient, seed: Seed) -> None:
    bad = {**SINE, "cue": {**SINE["cue"], "frequency_hz": -1.0}}
    response = client.post("/api/v1/prescriptions/preview", json={"segments": [SINE, bad]}, headers=seed.headers())
    assert response.status_code == 422
    locations = [".".join(map(str, item["loc"])) for item in response.json()["detail"]]
    assert any("segments[1].cue.frequency_hz" in loc or "segments.1.cue.frequency_hz" in loc for loc in locations)


def test_preview_api_answers_with_plot_data(client: TestClient, seed: Seed) -> None:
    patient_id = create_patient(client, seed.headers())
    response = client.post(
        "/api/v1/prescriptions/preview", json={"segments": [SINE], "patient_id": patient_id}, headers=seed.headers()
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["verdict"]["accepted"] is True and len(body["time_s"]) > 100


def test_preview_needs_a_login(client: TestClient) -> None:
    assert client.post("/api/v1/prescriptions/preview", json={"segments": [SINE]}).status_code == 401


def test_balance_of_a_run_is_the_sway_of_the_net_centre_of_pressure() -> None:
    n = 400
    time_s = np.arange(n) / 100.0
    forces = np.full((n, 2), 300.0)
    cops = np.zeros((n, 2, 2))
    cops[:, :, 0] = 0.01 * np.sin(2 * np.pi * 0.5 * time_s)[:, None]  # both feet sway 10 mm AP
    metrics = run_balance({"time_s": time_s, "plate_force_z_n": forces, "plate_cop_m": cops}, TWIN)
    assert metrics is not None
    assert metrics["range_ap_m"] == pytest.approx(0.02, rel=1e-3)
    assert metrics["range_ml_m"] == pytest.approx(0.0, abs=1e-12)  # equal loads: the feet's offsets cancel
    np.testing.assert_allclose(foot_origins_m(TWIN).sum(axis=0), 0.0)


def test_balance_needs_a_loaded_plate() -> None:
    columns = {"time_s": np.arange(10.0), "plate_force_z_n": np.zeros((10, 2)), "plate_cop_m": np.zeros((10, 2, 2))}
    assert run_balance(columns, TWIN) is None


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
