"""`/prescriptions`: validated by the core cue and washout validators, limits that may only tighten,
and versioning (editing adds a version; earlier versions stay as they were)."""

from __future__ import annotations

import math

import pytest
from fastapi.testclient import TestClient

from tests.server.conftest import SEGMENT, Seed, create_patient, create_prescription


def post(client: TestClient, seed: Seed, patient_id: int, segment: dict) -> object:
    body = {"patient_id": patient_id, "name": "P", "segments": [segment]}
    return client.post("/api/v1/prescriptions", json=body, headers=seed.headers())


def refused_field(response: object) -> str:
    """The refused field as the console names it (js/api.js fieldErrors): `segments[0].cue.frequency_hz`,
    whether the model (`["body", "segments", 0, ...]`) or a robot check (`["body", "segments[0]", ...]`) refused."""
    assert response.status_code == 422, response.text
    path = ""
    for part in response.json()["detail"][0]["loc"][1:]:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else part)
    return path


def test_a_prescription_is_stored_with_the_default_washout_filled_in(client: TestClient, seed: Seed) -> None:
    washout = pytest.importorskip("core.washout")
    patient_id = create_patient(client, seed.headers())
    prescription_id = create_prescription(client, seed.headers(), patient_id)
    current = client.get(f"/api/v1/prescriptions/{prescription_id}", headers=seed.headers()).json()["current"]
    segment = current["content"]["segments"][0]
    assert current["version"] == 1 and segment["cue"] == SEGMENT["cue"] and segment["limits"] == SEGMENT["limits"]
    assert segment["washout"] == washout.paper_tilt_parameters().to_dict()


def test_an_invalid_cue_is_refused_naming_the_field(client: TestClient, seed: Seed) -> None:
    pytest.importorskip("core.cues")
    patient_id = create_patient(client, seed.headers())
    too_fast = {**SEGMENT, "cue": {**SEGMENT["cue"], "frequency_hz": 50.0}}
    assert refused_field(post(client, seed, patient_id, too_fast)).startswith("segments[0].cue")
    unknown_kind = {**SEGMENT, "cue": {"kind": "teleport"}}
    assert refused_field(post(client, seed, patient_id, unknown_kind)).startswith("segments[0].cue")


def test_invalid_washout_parameters_are_refused_naming_the_field(client: TestClient, seed: Seed) -> None:
    washout = pytest.importorskip("core.washout")
    patient_id = create_patient(client, seed.headers())
    parameters = washout.paper_tilt_parameters().to_dict()
    bad = {**SEGMENT, "washout": {**parameters, "not_a_parameter": 1.0}}
    assert refused_field(post(client, seed, patient_id, bad)) == "segments[0].washout.not_a_parameter"


def test_limits_may_only_tighten_the_robots_own(client: TestClient, seed: Seed) -> None:
    patient_id = create_patient(client, seed.headers())
    looser = {**SEGMENT, "limits": {"tilt_max_rad": math.radians(40.0)}}  # the robot allows 25 degrees
    assert refused_field(post(client, seed, patient_id, looser)) == "segments[0].limits.tilt_max_rad"
    unknown = {**SEGMENT, "limits": {"warp_factor": 1.0}}
    assert refused_field(post(client, seed, patient_id, unknown)) == "segments[0].limits.warp_factor"
    assert client.get("/api/v1/prescriptions", headers=seed.headers()).json() == []


def test_structural_errors_name_the_field(client: TestClient, seed: Seed) -> None:
    patient_id = create_patient(client, seed.headers())
    assert refused_field(post(client, seed, patient_id, {**SEGMENT, "duration_s": -1})) == "segments[0].duration_s"
    empty = client.post(
        "/api/v1/prescriptions", json={"patient_id": patient_id, "name": "P", "segments": []}, headers=seed.headers()
    )
    assert refused_field(empty) == "segments"
    missing_patient = client.post(
        "/api/v1/prescriptions", json={"patient_id": 999999, "name": "P", "segments": [SEGMENT]}, headers=seed.headers()
    )
    assert missing_patient.status_code == 404


def test_editing_creates_a_new_version_and_keeps_the_old_one(client: TestClient, seed: Seed) -> None:
    headers = seed.headers()
    prescription_id = create_prescription(client, headers, create_patient(client, headers))
    longer = {**SEGMENT, "duration_s": 90.0}
    revised = client.put(
        f"/api/v1/prescriptions/{prescription_id}",
        json={"segments": [longer], "note": "longer"},
        headers={**headers, "If-Match": '"1"'},
    )
    assert revised.status_code == 200
    assert revised.json()["latest_version"] == 2 and revised.json()["current"]["note"] == "longer"
    first = client.get(f"/api/v1/prescriptions/{prescription_id}/versions/1", headers=headers).json()
    assert first["content"]["segments"][0]["duration_s"] == SEGMENT["duration_s"]
    versions = client.get(f"/api/v1/prescriptions/{prescription_id}/versions", headers=headers).json()
    assert [v["version"] for v in versions] == [1, 2]
    assert client.get(f"/api/v1/prescriptions/{prescription_id}/versions/3", headers=headers).status_code == 404
    assert (
        client.put(
            "/api/v1/prescriptions/999999", json={"segments": [longer], "expected_version": 1}, headers=headers
        ).status_code
        == 404
    )


def test_a_revision_that_omits_the_cueing_and_seed_keeps_the_current_ones(client: TestClient, seed: Seed) -> None:
    """An edit that sends only new segments must not switch an optimal prescription back to classical."""
    headers = seed.headers()
    body = {"patient_id": create_patient(client, headers), "name": "P", "segments": [SEGMENT], "cueing": "optimal"}
    created = client.post("/api/v1/prescriptions", json={**body, "seed": 7}, headers=headers)
    assert created.status_code == 201, created.text
    url = f"/api/v1/prescriptions/{created.json()['id']}"
    kept = client.put(url, json={"segments": [{**SEGMENT, "duration_s": 90.0}], "expected_version": 1}, headers=headers)
    kept = kept.json()["current"]
    assert (kept["content"]["cueing"], kept["content"]["seed"]) == ("optimal", 7)
    changed = client.put(
        url, json={"segments": [SEGMENT], "cueing": "classical", "seed": 0, "expected_version": 2}, headers=headers
    )
    assert (changed.json()["current"]["content"]["cueing"], changed.json()["current"]["content"]["seed"]) == (
        "classical",
        0,
    )
