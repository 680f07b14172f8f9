"""Lost updates (issue 20 defect 15): two changes based on one version never both land. Patients and
prescriptions carry their version in the ETag; a change sends it back (If-Match or expected_version)."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from sqlalchemy.orm import Session
from sqlalchemy.orm.exc import StaleDataError

from server.db import upgrade_database
from server.patients.models import Patient
from tests.server.conftest import (
    SEGMENT,
    Seed,
    create_patient,
    create_prescription,
    scratch_database,
)


def test_two_prescription_revisions_based_on_one_version(client: TestClient, seed: Seed) -> None:
    headers = seed.headers()
    prescription_id = create_prescription(client, headers, create_patient(client, headers))
    mine = {"segments": [{**SEGMENT, "duration_s": 40.0}], "note": "mine"}
    theirs = {"segments": [{**SEGMENT, "duration_s": 50.0}], "note": "theirs"}
    first = client.put(f"/api/v1/prescriptions/{prescription_id}", json=mine, headers={**headers, "If-Match": '"1"'})
    second = client.put(
        f"/api/v1/prescriptions/{prescription_id}", json=theirs, headers={**seed.headers("admin"), "If-Match": '"1"'}
    )
    assert (first.status_code, second.status_code) == (200, 412), second.text
    assert first.headers["ETag"] == '"2"'
    refusal = second.json()
    assert refusal["current_version"] == 2 and refusal["changed_by"] == "therapist"
    assert "version 2" in refusal["detail"] and "based on version 1" in refusal["detail"], refusal["detail"]
    assert second.headers["ETag"] == '"2"'
    current = client.get(f"/api/v1/prescriptions/{prescription_id}", headers=headers)
    assert current.json()["latest_version"] == 2 and current.json()["current"]["note"] == "mine"
    assert current.headers["ETag"] == '"2"'


def test_a_revision_names_its_version_or_is_refused(client: TestClient, seed: Seed) -> None:
    headers = seed.headers()
    prescription_id = create_prescription(client, headers, create_patient(client, headers))
    body = {"segments": [SEGMENT]}
    missing = client.put(f"/api/v1/prescriptions/{prescription_id}", json=body, headers=headers)
    assert missing.status_code == 428, missing.text
    assert "If-Match" in missing.json()["detail"]
    in_body = client.put(
        f"/api/v1/prescriptions/{prescription_id}", json={**body, "expected_version": 1}, headers=headers
    )
    assert in_body.status_code == 200, in_body.text
    stale = client.put(
        f"/api/v1/prescriptions/{prescription_id}", json={**body, "expected_version": 1}, headers=headers
    )
    assert stale.status_code == 412
    assert client.get(f"/api/v1/prescriptions/{prescription_id}", headers=headers).json()["latest_version"] == 2


def test_two_patient_changes_based_on_one_version(client: TestClient, seed: Seed) -> None:
    headers = seed.headers()
    patient_id = create_patient(client, headers)
    url = f"/api/v1/patients/{patient_id}"
    first = client.patch(url, json={"notes": "first"}, headers={**headers, "If-Match": '"1"'})
    second = client.patch(url, json={"body_mass_kg": 70.0}, headers={**seed.headers("admin"), "If-Match": '"1"'})
    assert (first.status_code, second.status_code) == (200, 412), second.text
    assert first.headers["ETag"] == '"2"' and first.json()["version"] == 2
    assert second.json()["current_version"] == 2 and second.json()["changed_by"] == "therapist"
    stored = client.get(url, headers=headers)
    assert stored.json()["notes"] == "first" and stored.json()["body_mass_kg"] == 60.0
    assert stored.headers["ETag"] == '"2"'
    assert client.patch(url, json={"notes": "x"}, headers=headers).status_code == 428
    archived = client.patch(url, json={"archived": True, "expected_version": 2}, headers=headers)
    assert archived.status_code == 200 and archived.json()["version"] == 3


@pytest.mark.postgres
def test_the_database_refuses_the_second_of_two_racing_updates(tmp_path: Path) -> None:
    """Past the service's check (two transactions read version 1 at once, as PostgreSQL's read committed
    allows; SQLite's BEGIN IMMEDIATE serialises them before the check): each UPDATE names the version it
    read, so the second changes no row and is refused (412), never applied."""
    scratch = scratch_database("postgresql", tmp_path)
    try:
        upgrade_database(scratch.engine)
        with Session(scratch.engine) as setup:
            patient = Patient(identifier="MRN-RACE", name="Race", date_of_birth=dt.date(1950, 1, 1), sex="female",
                              height_m=1.6, body_mass_kg=60.0)  # fmt: skip
            setup.add(patient)
            setup.commit()
            patient_id = patient.id
        with Session(scratch.engine) as first, Session(scratch.engine) as second:
            mine, theirs = first.get(Patient, patient_id), second.get(Patient, patient_id)
            assert mine is not None and theirs is not None and mine.version == theirs.version == 1
            mine.notes, theirs.notes = "first", "second"
            first.commit()
            with pytest.raises(StaleDataError):
                second.commit()
        with Session(scratch.engine) as check:
            stored = check.get(Patient, patient_id)
            assert stored is not None and (stored.notes, stored.version) == ("first", 2)
    finally:
        scratch.drop()
