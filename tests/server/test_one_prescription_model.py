"""Issue 14 §1: the prescription is validated once, by one model (`core.plan.prescription`), and one pipeline
(`core.plan.build.build_plan`) turns it into the plan that the preview shows, the offline check passes and the
worker plays.

Defects this reproduces (each failed before the change): shaping could not be set through the API (422,
"extra inputs"); the API refused more than 50 segments while the real-time side allowed 100; the preview, the
offline check and the worker each assembled the timeline themselves."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from core.plan.build import build_plan, plan_prescription
from core.plan.prescription import SEGMENT_COUNT_MAX, PrescriptionError, parse_prescription
from core.plan.timeline import prescription_timeline
from core.robot import TwinRobot, default_twin
from core.shaping import ShapingParameters
from server.hal.kinematic import KinematicHal
from server.prescriptions.preview import prescription_preview
from server.realtime.pipeline import TickPipeline, start_along_checked_approach
from server.realtime.supervisor import SupervisorConfig
from server.realtime.telemetry import SupervisorState
from tests.server.conftest import SEGMENT, Seed, create_patient

SHORT = {"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.3, "frequency_hz": 0.5}, "duration_s": 1.0}
NOTCH = {"kind": "notch", "notch_frequency_hz": 9.7559, "notch_quality": 0.4}


@pytest.fixture(scope="module")
def twin() -> TwinRobot:
    return default_twin()


def _post(client: TestClient, seed: Seed, segments: list[dict[str, Any]]) -> Any:
    found = client.get("/api/v1/patients", headers=seed.headers()).json()
    patient_id = found[0]["id"] if found else create_patient(client, seed.headers())
    body = {"patient_id": patient_id, "name": "P", "segments": segments}
    return client.post("/api/v1/prescriptions", json=body, headers=seed.headers())


# --- defect (a): shaping through the API ------------------------------------------------------------------


def test_shaping_set_through_the_api_is_stored_and_planned(client: TestClient, seed: Seed, twin: TwinRobot) -> None:
    response = _post(client, seed, [{**SEGMENT, "shaping": NOTCH}])
    assert response.status_code == 201, response.text
    stored = response.json()["current"]["content"]
    assert stored["segments"][0]["shaping"] == ShapingParameters(**NOTCH).to_dict()
    # The stored content is what the robot daemon plans from: the notch reaches the worker's shaper.
    plan = plan_prescription(stored, twin)
    assert plan.segments[0].shaping == ShapingParameters(**NOTCH)


def test_invalid_shaping_is_refused_naming_the_field_before_any_write(client: TestClient, seed: Seed) -> None:
    bad = _post(client, seed, [{**SEGMENT, "shaping": {"lowpass_order": 12}}])
    assert bad.status_code == 422
    detail = bad.json()["detail"][0]
    assert detail["loc"] == ["body", "segments", 0, "shaping", "lowpass_order"]
    assert "segments[0].shaping.lowpass_order = 12" in detail["msg"] and "8" in detail["msg"]
    # Too high a cut-off for the first mode at the robot's control rate: the robot-dependent step refuses it.
    exposed = _post(client, seed, [{**SEGMENT, "shaping": {"lowpass_cutoff_hz": 9.0}}])
    assert exposed.status_code == 422
    assert exposed.json()["detail"][0]["loc"][1:3] == ["segments[0]", "shaping"]
    assert client.get("/api/v1/prescriptions", headers=seed.headers()).json() == []


def test_a_csv_cue_is_parsed_in_the_requests_thread_not_by_the_model(client: TestClient, seed: Seed) -> None:
    """The API validates bodies on its event loop: the model only bounds the CSV's size; its rows are parsed by
    the check before the write (in the request's worker thread), with the same error shape."""
    header = "time_s,specific_force_x_m_s2,specific_force_y_m_s2,specific_force_z_m_s2"
    segment = {"cue": {"kind": "csv_replay", "csv": f"{header}\n0,0,0,0\n1,0,99,0\n"}, "duration_s": 5.0}
    assert parse_prescription({"segments": [segment]}).segments[0].cue.check_deferred
    refused = _post(client, seed, [segment])
    assert refused.status_code == 422
    detail = refused.json()["detail"][0]
    assert detail["loc"] == ["body", "segments[0]", "cue", "csv[2]", "specific_force_y_m_s2"]
    assert "99" in detail["msg"] and "[-10, 10]" in detail["msg"]
    assert client.get("/api/v1/prescriptions", headers=seed.headers()).json() == []


# --- defect (b): one segment limit ---------------------------------------------------------------------------


def test_the_api_and_the_robot_accept_the_same_number_of_segments(
    client: TestClient, seed: Seed, twin: TwinRobot
) -> None:
    assert SEGMENT_COUNT_MAX == 100
    accepted = _post(client, seed, [SHORT] * 51)  # the API used to stop at 50
    assert accepted.status_code == 201, accepted.text
    assert len(plan_prescription(accepted.json()["current"]["content"], twin).segments) == 51
    too_many = [SHORT] * (SEGMENT_COUNT_MAX + 1)
    refused = _post(client, seed, too_many)
    assert refused.status_code == 422 and refused.json()["detail"][0]["loc"] == ["body", "segments"]
    assert str(SEGMENT_COUNT_MAX) in refused.json()["detail"][0]["msg"]
    with pytest.raises(PrescriptionError) as offline:
        parse_prescription({"segments": too_many})
    assert offline.value.field == "segments" and str(SEGMENT_COUNT_MAX) in offline.value.limit
    schema = client.get("/openapi.json").json()["components"]["schemas"]
    for body in ("PrescriptionCreate", "PrescriptionRevise", "PreviewRequest"):
        assert schema[body]["properties"]["segments"]["maxItems"] == SEGMENT_COUNT_MAX


# --- defect (c): one pipeline for the preview, the offline check and the worker ---------------------------------


def _played(twin: TwinRobot, plan: Any, ticks: int) -> np.ndarray:
    """The stance pose the worker's tick pipeline commands at every tick from the first cue tick on."""
    hal = KinematicHal(twin, plan.sample_period_s, communication_timeout_s=60.0)
    hal.configure()
    pipeline = TickPipeline(twin, hal, plan.control_rate_hz, SupervisorConfig(), lambda *_: None)
    pipeline.load(plan)
    pipeline.heartbeat()
    start_along_checked_approach(pipeline)
    poses, cueing = [], False
    for _ in range(ticks):
        pipeline.heartbeat()
        pipeline.tick(0)
        # From the plan's first sample on (after the approach).
        cueing = cueing or pipeline.source.plan_index >= 0
        if cueing and pipeline.wrote_this_tick:
            poses.append(pipeline.pose.copy())
        if pipeline.supervisor.state is SupervisorState.STOPPED:  # the plan's last sample ended it
            break
    return np.array(poses)


@pytest.mark.parametrize("cueing", ["classical", "optimal"])
def test_the_worker_plays_the_plan_the_preview_shows_and_the_check_passed(twin: TwinRobot, cueing: str) -> None:
    prescription = {
        "cueing": cueing,
        "segments": [
            {"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.4, "frequency_hz": 0.5}, "duration_s": 3.0},
            {"cue": {"kind": "step", "axis": "x", "final_m_s2": 0.3, "end_time_s": 1.5}, "duration_s": 2.0},
        ],
    }
    checked = build_plan(prescription, twin, control_rate_hz=250, config=SupervisorConfig())
    report = checked.accepted()
    timeline = prescription_timeline(checked.plan)
    assert report.samples == len(timeline["poses"])  # the check ran over exactly this timeline
    played = _played(twin, checked.plan, report.samples + 500)
    assert len(played) == report.samples
    # Sample for sample: cue phases and returns to neutral of both segments.
    np.testing.assert_allclose(played, timeline["poses"], rtol=0.0, atol=1e-9)
    preview = prescription_preview(parse_prescription(prescription), twin, control_rate_hz=250)
    assert preview["verdict"] == {"accepted": True, "report": report.to_dict()}
    shown = np.array(preview["platform_position_m"], dtype=float).T
    rows = np.round(np.array(preview["time_s"]) * 250).astype(int)
    np.testing.assert_allclose(shown, timeline["poses"][rows, :3], atol=1e-6)  # the preview rounds to µm


# --- stored content ------------------------------------------------------------------------------------------


def test_stored_content_round_trips_and_old_versions_without_shaping_load(twin: TwinRobot) -> None:
    content = parse_prescription({"segments": [SEGMENT], "cueing": "optimal", "seed": 3}).content()
    assert parse_prescription(content).content() == content
    # A version stored before issue 14 §1: no shaping, no seed (validation.py's output).
    old = {"segments": [{k: v for k, v in content["segments"][0].items() if k != "shaping"}], "cueing": "classical"}
    loaded = parse_prescription(old)
    assert loaded.segments[0].shaping.parameters() == ShapingParameters() and loaded.seed == 0
    assert loaded.segments[0].cue.spec() == SEGMENT["cue"] and loaded.segments[0].limit_overrides() == SEGMENT["limits"]


def test_the_api_documents_every_cue_kind_with_units(client: TestClient) -> None:
    schemas = client.get("/openapi.json").json()["components"]["schemas"]
    cue = schemas["Segment"]["properties"]["cue"]
    assert cue["discriminator"]["propertyName"] == "kind"
    kinds = set(cue["discriminator"]["mapping"])
    assert kinds == {"square_wave", "step", "sine", "multisine", "gait", "perturbations", "csv_replay"}
    sine = schemas["SineCue"]["properties"]
    assert "Hz" in sine["frequency_hz"]["description"] and sine["frequency_hz"]["maximum"] == 5.0
    assert "m/s²" in sine["amplitude_m_s2"]["description"] and "rad/s" in sine["amplitude_rad_s"]["description"]
    assert set(schemas["Segment"]["properties"]) == {"cue", "duration_s", "washout", "shaping", "limits"}
    assert "rad/s" in schemas["Washout"]["properties"]["tilt_break_rad_s"]["description"]
    assert schemas["Shaping"]["properties"]["lowpass_order"]["maximum"] == 8
    assert set(schemas["Limits"]["properties"]) >= {"tilt_max_rad", "slider_velocity_max_m_s"}
