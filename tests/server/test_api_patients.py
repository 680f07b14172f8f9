"""`/patients`: CRUD, refusals naming the field, 404/409, and the audit trail of reads and changes."""

from __future__ import annotations

from fastapi.testclient import TestClient

from tests.server.conftest import PATIENT, Seed, booked_session, create_patient


def audit(client: TestClient, seed: Seed, **filters: object) -> list[dict]:
    response = client.get("/api/v1/audit", params=filters, headers=seed.headers("admin"))
    assert response.status_code == 200
    return response.json()


def test_create_read_update_and_list_patients(client: TestClient, seed: Seed) -> None:
    headers = seed.headers()
    patient_id = create_patient(client, headers)
    read = client.get(f"/api/v1/patients/{patient_id}", headers=headers).json()
    assert {k: read[k] for k in PATIENT} == PATIENT
    updated = client.patch(
        f"/api/v1/patients/{patient_id}", json={"body_mass_kg": 61.5, "expected_version": 1}, headers=headers
    )
    assert updated.status_code == 200 and updated.json()["body_mass_kg"] == 61.5
    create_patient(client, headers, identifier="MRN-0002", name="Other Person", diagnosis="Parkinson")
    found = client.get("/api/v1/patients", params={"search": "greta"}, headers=headers).json()
    assert [p["id"] for p in found] == [patient_id]
    by_diagnosis = client.get("/api/v1/patients", params={"diagnosis": "parkinson"}, headers=headers).json()
    assert [p["identifier"] for p in by_diagnosis] == ["MRN-0002"]


def test_invalid_fields_are_refused_with_422_naming_each_field(client: TestClient, seed: Seed) -> None:
    bad = {**PATIENT, "height_m": 7.0, "sex": "f", "date_of_birth": "2999-01-01", "unexpected": 1}
    response = client.post("/api/v1/patients", json=bad, headers=seed.headers())
    assert response.status_code == 422
    named = {tuple(error["loc"]) for error in response.json()["detail"]}
    assert {("body", "height_m"), ("body", "sex"), ("body", "date_of_birth"), ("body", "unexpected")} <= named
    assert client.get("/api/v1/patients", headers=seed.headers()).json() == []  # nothing half-written


def test_non_finite_numbers_are_refused(client: TestClient, seed: Seed) -> None:
    body = (
        '{"identifier": "X-1", "name": "N", "date_of_birth": "1950-01-01", "sex": "male",'
        ' "height_m": NaN, "body_mass_kg": 70}'
    )
    response = client.post(
        "/api/v1/patients", content=body, headers={**seed.headers(), "Content-Type": "application/json"}
    )
    assert response.status_code == 422
    assert ["body", "height_m"] in [error["loc"] for error in response.json()["detail"]]


def test_unknown_ids_give_404_and_duplicates_409(client: TestClient, seed: Seed) -> None:
    headers = seed.headers()
    assert client.get("/api/v1/patients/999999", headers=headers).status_code == 404
    assert (
        client.patch("/api/v1/patients/999999", json={"notes": "x", "expected_version": 1}, headers=headers).status_code
        == 404
    )
    create_patient(client, headers)
    duplicate = client.post("/api/v1/patients", json=PATIENT, headers=headers)
    assert duplicate.status_code == 409 and duplicate.json()["field"] == "identifier"


def test_a_patient_with_sessions_cannot_be_deleted(client: TestClient, seed: Seed) -> None:
    headers = seed.headers()
    booked = booked_session(client, headers)
    assert client.delete(f"/api/v1/patients/{booked.patient_id}", headers=headers).status_code == 409
    lone = create_patient(client, headers, identifier="MRN-LONE")
    assert client.delete(f"/api/v1/patients/{lone}", headers=headers).status_code == 204
    assert client.get(f"/api/v1/patients/{lone}", headers=headers).status_code == 404


def test_reads_and_changes_of_patient_records_are_audited_without_patient_data(client: TestClient, seed: Seed) -> None:
    headers = seed.headers()
    patient_id = create_patient(client, headers)
    client.get(f"/api/v1/patients/{patient_id}", headers=headers)
    client.patch(
        f"/api/v1/patients/{patient_id}", json={"notes": "dizzy today", "expected_version": 1}, headers=headers
    )
    client.get("/api/v1/patients", headers=headers)
    entries = audit(client, seed, resource_type="patient")
    actions = [(e["action"], e["resource_id"], e["user_id"]) for e in reversed(entries)]
    assert actions == [
        ("create", patient_id, seed.therapist_id),
        ("read", patient_id, seed.therapist_id),
        ("update", patient_id, seed.therapist_id),
        ("list", None, seed.therapist_id),
    ]
    assert entries[0]["details"] == {"patient_ids": [patient_id]}
    assert entries[1]["details"] == {"fields": ["notes"]}
    text = str(entries)
    assert PATIENT["name"] not in text and "dizzy" not in text and PATIENT["identifier"] not in text
