"""Numbers are refused by name (issue 20, defect 9 / Build 11): a float that is not finite, not normal
(denormal) or outside its physical range is a 422 whose `loc` names the field, on every request model."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest
from fastapi.testclient import TestClient

from tests.server.conftest import SEGMENT, Seed, create_patient

DENORMAL = 5e-324


def prescription_post(client: TestClient, seed: Seed, segment: dict[str, Any]) -> Any:
    body = {"patient_id": create_patient(client, seed.headers()), "name": "P", "segments": [segment]}
    # Python's json writes NaN and Infinity as JavaScript does; a client may send them.
    headers = {**seed.headers(), "Content-Type": "application/json"}
    return client.post("/api/v1/prescriptions", content=json.dumps(body), headers=headers)


def refused_path(response: Any) -> str:
    assert response.status_code == 422, response.text
    path = ""
    for part in response.json()["detail"][0]["loc"][1:]:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else part)
    return path


def test_a_denormal_lowpass_cutoff_is_a_422_naming_the_field(client: TestClient, seed: Seed) -> None:
    response = prescription_post(client, seed, {**SEGMENT, "shaping": {"lowpass_cutoff_hz": DENORMAL}})
    assert refused_path(response) == "segments[0].shaping.lowpass_cutoff_hz"


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, -DENORMAL, 1e-310])
@pytest.mark.parametrize(
    ("where", "field"),
    [("shaping", "lowpass_cutoff_hz"), ("shaping", "notch_quality"), ("washout", "tilt_break_rad_s"),
     ("limits", "tilt_max_rad"), ("cue", "frequency_hz")],
)  # fmt: skip
def test_non_finite_and_subnormal_numbers_are_refused_at_their_field(
    client: TestClient, seed: Seed, where: str, field: str, value: float
) -> None:
    segment = {**SEGMENT, where: {**SEGMENT.get(where, {}), field: value}}
    response = prescription_post(client, seed, segment)
    assert refused_path(response) == f"segments[0].{where}.{field}"


def test_every_request_body_and_every_part_of_a_prescription_has_the_rule(client: TestClient) -> None:
    """The rule lives in one base (`core.validation.StrictModel`): every request body of the API and every
    model of a prescription derives from it."""
    from fastapi.routing import APIRoute
    from pydantic import BaseModel

    from core.plan import prescription
    from core.validation import StrictModel

    def routes(router: Any) -> list[APIRoute]:
        found = []
        for route in router.routes:
            inner = getattr(route, "original_router", None)  # an included router
            found += routes(inner) if inner is not None else [route] if isinstance(route, APIRoute) else []
        return found

    bodies = [route.body_field.field_info.annotation for route in routes(client.app.router) if route.body_field]
    parts = [m for m in vars(prescription).values() if isinstance(m, type) and issubclass(m, BaseModel)]
    parts.remove(BaseModel)
    assert len(bodies) >= 9 and len(parts) >= 10
    assert [m for m in bodies + parts if not (isinstance(m, type) and issubclass(m, StrictModel))] == []


SWEPT_FIELDS = [
    ("shaping", "lowpass_cutoff_hz"), ("shaping", "notch_frequency_hz"), ("shaping", "notch_quality"),
    ("shaping", "first_mode_hz"), ("shaping", "required_attenuation_db"), ("shaping", "mode_band_fraction"),
    ("washout", "tilt_break_rad_s"), ("washout", "translational_damping"), ("washout", "specific_force_gain"),
    ("washout", "specific_force_limit_m_s2"), ("washout", "head_height_m"),
    ("limits", "tilt_max_rad"), ("limits", "drive_force_max_n"), ("cue", "frequency_hz"), ("cue", "phase_rad"),
    (None, "duration_s"),
]  # fmt: skip


def test_a_sweep_of_any_float_into_any_field_is_stored_or_refused_at_that_field(client: TestClient, seed: Seed) -> None:
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    patient_id = create_patient(client, seed.headers())
    headers = {**seed.headers(), "Content-Type": "application/json"}
    special = st.sampled_from([DENORMAL, -DENORMAL, 1e-308, 2.2250738585072014e-308, 1e-300, 1e300, 0.0, -0.0])

    @given(place=st.sampled_from(SWEPT_FIELDS), value=st.floats(allow_subnormal=True) | special)
    @settings(max_examples=150, deadline=None, derandomize=True, database=None,
              suppress_health_check=list(HealthCheck))  # fmt: skip
    def one(place: tuple[str | None, str], value: float) -> None:
        where, field = place
        block = {field: value} if where is None else {where: {**SEGMENT.get(where, {}), field: value}}
        segment = {**SEGMENT, **block}
        body = {"patient_id": patient_id, "name": "P", "segments": [segment]}
        response = client.post("/api/v1/prescriptions", content=json.dumps(body), headers=headers)
        assert response.status_code in (201, 422), (place, value, response.text)
        if response.status_code == 422:
            assert refused_path(response).startswith("segments[0]"), (place, value, response.text)

    one()
