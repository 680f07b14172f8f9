"""A segment that is stored can start (issue 20, defect 19): a 3600 s segment was stored (201) and its start
refused (409 "duration_s = 3601.0"), because the cue is generated for the duration plus the fade out. The
model's limit leaves room for the longest fade out a plan may have: one rule, in core.plan."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from core import cues
from core.plan.build import plan_prescription
from core.plan.config import FADE_OUT_MAX_S, PlanConfig, PlanConfigError
from core.plan.prescription import SEGMENT_DURATION_MAX_S
from core.robot import default_twin
from tests.server.conftest import SEGMENT, Seed, create_patient


def test_a_segment_too_long_to_start_is_refused_when_it_is_saved(client: TestClient, seed: Seed) -> None:
    body = {"patient_id": create_patient(client, seed.headers()), "name": "P",
            "segments": [{**SEGMENT, "duration_s": cues.CUE_TIME_MAX_S}]}  # fmt: skip
    response = client.post("/api/v1/prescriptions", json=body, headers=seed.headers())
    assert response.status_code == 422, response.text
    error = response.json()["detail"][0]
    assert error["loc"][1:] == ["segments", 0, "duration_s"]
    assert "3600" in error["msg"] and f"{SEGMENT_DURATION_MAX_S:g}" in error["msg"], error["msg"]


def test_the_longest_segment_with_the_longest_fade_out_fits_the_cue_generator() -> None:
    prescription = {"segments": [{**SEGMENT, "duration_s": SEGMENT_DURATION_MAX_S}]}
    config = PlanConfig(fade_out_s=FADE_OUT_MAX_S)
    plan = plan_prescription(prescription, default_twin(), config=config)
    rate = plan.control_rate_hz
    # What the start's cue generation checks first (core.cues.CueGenerator.generate).
    assert 0 < plan.segments[0].cue_samples * (1.0 / rate) <= cues.CUE_TIME_MAX_S
    with pytest.raises(PlanConfigError, match="fade_out_s"):
        PlanConfig(fade_out_s=FADE_OUT_MAX_S * 1.01)
