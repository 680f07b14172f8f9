"""`/sessions` (scheduled): bookings, recurring series, conflict detection (409, nothing written),
rescheduling, cancelling a series, schedule queries and the therapist's iCalendar feed."""

from __future__ import annotations

from fastapi.testclient import TestClient
from icalendar import Calendar

from tests.server.conftest import PATIENT, Seed, book, create_patient, create_prescription

MONDAY_9 = "2031-05-05T09:00:00+00:00"


def patient_with_prescription(client: TestClient, seed: Seed, identifier: str = "MRN-A") -> tuple[int, int]:
    patient_id = create_patient(client, seed.headers(), identifier=identifier)
    return patient_id, create_prescription(client, seed.headers(), patient_id)


def all_sessions(client: TestClient, seed: Seed) -> list[dict]:
    return client.get("/api/v1/sessions", headers=seed.headers()).json()


def test_booking_records_the_prescription_version_in_utc(client: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_with_prescription(client, seed)
    response = book(
        client,
        seed.headers(),
        patient_id=patient_id,
        prescription_id=prescription_id,
        start="2031-05-05T11:00:00+02:00",
    )
    assert response.status_code == 201
    (booking,) = response.json()
    assert booking["start"] == "2031-05-05T09:00:00Z" and booking["end"] == "2031-05-05T09:30:00Z"
    assert booking["prescription_version"] == 1 and booking["therapist_id"] == seed.therapist_id
    client.put(
        f"/api/v1/prescriptions/{prescription_id}",
        json={
            "segments": [
                {"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.3, "frequency_hz": 0.5}, "duration_s": 20.0}
            ]
        },
        headers=seed.headers(),
    )
    kept = client.get(f"/api/v1/sessions/{booking['id']}", headers=seed.headers()).json()
    assert kept["prescription_version"] == 1  # editing the prescription does not change a booked session


def test_robot_double_booking_is_a_409(client: TestClient, seed: Seed) -> None:
    first_patient, first_prescription = patient_with_prescription(client, seed, "MRN-A")
    other_patient, other_prescription = patient_with_prescription(client, seed, "MRN-B")
    assert (
        book(
            client, seed.headers(), patient_id=first_patient, prescription_id=first_prescription, start=MONDAY_9
        ).status_code
        == 201
    )
    clash = book(
        client,
        seed.headers(),
        patient_id=other_patient,
        prescription_id=other_prescription,
        start="2031-05-05T09:29:00+00:00",
    )
    assert clash.status_code == 409 and clash.json()["field"] == "robot"
    elsewhere = book(
        client,
        seed.headers(),
        patient_id=other_patient,
        prescription_id=other_prescription,
        start="2031-05-05T09:29:00+00:00",
        robot="twin-2",
    )
    assert elsewhere.status_code == 201
    back_to_back = book(
        client,
        seed.headers(),
        patient_id=other_patient,
        prescription_id=other_prescription,
        start="2031-05-05T08:30:00+00:00",
    )
    assert back_to_back.status_code == 201  # [start, end) intervals: touching is not overlapping


def test_patient_double_booking_is_a_409_even_on_another_robot(client: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_with_prescription(client, seed)
    book(client, seed.headers(), patient_id=patient_id, prescription_id=prescription_id, start=MONDAY_9)
    clash = book(
        client,
        seed.headers(),
        patient_id=patient_id,
        prescription_id=prescription_id,
        start="2031-05-05T08:45:00+00:00",
        robot="twin-2",
    )
    assert clash.status_code == 409 and clash.json()["field"] == "patient_id"


def test_a_recurring_series_is_booked_whole_or_not_at_all(client: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_with_prescription(client, seed, "MRN-A")
    other_patient, other_prescription = patient_with_prescription(client, seed, "MRN-B")
    # Another patient already holds the robot in the third week.
    book(
        client,
        seed.headers(),
        patient_id=other_patient,
        prescription_id=other_prescription,
        start="2031-05-19T09:15:00+00:00",
    )
    weekly = {"frequency": "weekly", "interval": 1, "count": 4}
    clash = book(
        client,
        seed.headers(),
        patient_id=patient_id,
        prescription_id=prescription_id,
        start=MONDAY_9,
        recurrence=weekly,
    )
    assert clash.status_code == 409 and "occurrence 3 of 4" in clash.json()["detail"]
    assert len(all_sessions(client, seed)) == 1
    series = book(
        client,
        seed.headers(),
        patient_id=patient_id,
        prescription_id=prescription_id,
        start="2031-05-05T07:00:00+00:00",
        recurrence=weekly,
    )
    assert series.status_code == 201
    starts = [b["start"] for b in series.json()]
    assert starts == ["2031-05-05T07:00:00Z", "2031-05-12T07:00:00Z", "2031-05-19T07:00:00Z", "2031-05-26T07:00:00Z"]
    series_id = series.json()[0]["series_id"]
    assert {b["series_id"] for b in series.json()} == {series_id}
    cancelled = client.post(f"/api/v1/series/{series_id}/cancel", headers=seed.headers())
    assert [b["status"] for b in cancelled.json()] == ["cancelled"] * 4
    # Cancelled bookings free the slot.
    again = book(
        client,
        seed.headers(),
        patient_id=patient_id,
        prescription_id=prescription_id,
        start="2031-05-12T07:00:00+00:00",
    )
    assert again.status_code == 201


def test_rescheduling_into_a_taken_slot_is_a_409_and_changes_nothing(client: TestClient, seed: Seed) -> None:
    patient_a, prescription_a = patient_with_prescription(client, seed, "MRN-A")
    patient_b, prescription_b = patient_with_prescription(client, seed, "MRN-B")
    book(client, seed.headers(), patient_id=patient_a, prescription_id=prescription_a, start=MONDAY_9)
    later = book(
        client, seed.headers(), patient_id=patient_b, prescription_id=prescription_b, start="2031-05-05T10:00:00+00:00"
    ).json()[0]
    moved = client.patch(
        f"/api/v1/sessions/{later['id']}", json={"start": "2031-05-05T09:10:00+00:00"}, headers=seed.headers()
    )
    assert moved.status_code == 409
    assert client.get(f"/api/v1/sessions/{later['id']}", headers=seed.headers()).json()["start"] == later["start"]
    longer = client.patch(f"/api/v1/sessions/{later['id']}", json={"duration_s": 3600}, headers=seed.headers())
    assert longer.status_code == 200 and longer.json()["end"] == "2031-05-05T11:00:00Z"


def test_invalid_bookings_are_refused_naming_the_field(client: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_with_prescription(client, seed, "MRN-A")
    other_patient = create_patient(client, seed.headers(), identifier="MRN-B")
    wrong_owner = book(client, seed.headers(), patient_id=other_patient, prescription_id=prescription_id)
    assert wrong_owner.status_code == 422 and wrong_owner.json()["detail"][0]["loc"] == ["body", "prescription_id"]
    naive = book(
        client, seed.headers(), patient_id=patient_id, prescription_id=prescription_id, start="2031-05-05T09:00:00"
    )
    assert naive.status_code == 422 and naive.json()["detail"][0]["loc"] == ["body", "start"]
    short = book(client, seed.headers(), patient_id=patient_id, prescription_id=prescription_id, duration_s=5)
    assert short.status_code == 422 and short.json()["detail"][0]["loc"] == ["body", "duration_s"]
    unknown = book(client, seed.headers(), patient_id=patient_id, prescription_id=999999)
    assert unknown.status_code == 404
    assert all_sessions(client, seed) == []


def test_schedule_queries_filter_by_window_robot_and_patient(client: TestClient, seed: Seed) -> None:
    patient_a, prescription_a = patient_with_prescription(client, seed, "MRN-A")
    patient_b, prescription_b = patient_with_prescription(client, seed, "MRN-B")
    book(client, seed.headers(), patient_id=patient_a, prescription_id=prescription_a, start=MONDAY_9)
    book(
        client,
        seed.headers(),
        patient_id=patient_b,
        prescription_id=prescription_b,
        start="2031-05-06T09:00:00+00:00",
        robot="twin-2",
    )

    def query(**params: object) -> list[int]:
        response = client.get("/api/v1/sessions", params=params, headers=seed.headers())
        assert response.status_code == 200, response.text
        return [b["patient_id"] for b in response.json()]

    assert query() == [patient_a, patient_b]
    assert query(**{"from": "2031-05-06T00:00:00Z", "to": "2031-05-07T00:00:00Z"}) == [patient_b]
    assert query(robot="twin-1") == [patient_a]
    assert query(patient_id=patient_b) == [patient_b]
    assert client.get("/api/v1/sessions", params={"from": "yesterday"}, headers=seed.headers()).status_code == 422


def test_the_therapist_calendar_feed_is_valid_icalendar_without_patient_names(client: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_with_prescription(client, seed, "MRN-A")
    book(
        client,
        seed.headers(),
        patient_id=patient_id,
        prescription_id=prescription_id,
        start=MONDAY_9,
        recurrence={"frequency": "daily", "interval": 2, "count": 3},
    )
    response = client.get(f"/api/v1/therapists/{seed.therapist_id}/calendar.ics", headers=seed.headers())
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/calendar")
    events = Calendar.from_ical(response.content).walk("VEVENT")
    assert [e.decoded("dtstart").isoformat() for e in events] == [
        "2031-05-05T09:00:00+00:00",
        "2031-05-07T09:00:00+00:00",
        "2031-05-09T09:00:00+00:00",
    ]
    assert all("MRN-A" in str(e["summary"]) for e in events)
    assert PATIENT["name"] not in response.text
    admin_feed = client.get(f"/api/v1/therapists/{seed.admin_id}/calendar.ics", headers=seed.headers("admin"))
    assert Calendar.from_ical(admin_feed.content).walk("VEVENT") == []
    assert client.get("/api/v1/therapists/999999/calendar.ics", headers=seed.headers("admin")).status_code == 404


def test_a_therapist_cannot_read_another_therapists_feed(client: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_with_prescription(client, seed, "MRN-A")
    book(client, seed.headers("admin"), patient_id=patient_id, prescription_id=prescription_id, start=MONDAY_9)
    other = client.get(f"/api/v1/therapists/{seed.admin_id}/calendar.ics", headers=seed.headers())
    assert other.status_code == 403, other.text
    assert "therapist_id" in other.json()["detail"]
    own = client.get(f"/api/v1/therapists/{seed.admin_id}/calendar.ics", headers=seed.headers("admin"))
    assert own.status_code == 200


def test_a_subscription_link_serves_only_that_therapists_feed_without_a_login(client: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_with_prescription(client, seed, "MRN-A")
    book(client, seed.headers(), patient_id=patient_id, prescription_id=prescription_id, start=MONDAY_9)
    book(client, seed.headers("admin"), patient_id=patient_id, prescription_id=prescription_id,
         start="2031-05-06T09:00:00+00:00")  # fmt: skip
    # A calendar app has no login: the feed's login URL refuses it.
    assert client.get(f"/api/v1/therapists/{seed.therapist_id}/calendar.ics").status_code == 401
    issued = client.post(f"/api/v1/therapists/{seed.therapist_id}/calendar-subscription", headers=seed.headers())
    assert issued.status_code == 201, issued.text
    url = issued.json()["url"]
    assert url.startswith("http") and url.endswith(".ics")
    feed = client.get(url)  # no Authorization header, no cookie
    assert feed.status_code == 200 and feed.headers["content-type"].startswith("text/calendar")
    events = Calendar.from_ical(feed.content).walk("VEVENT")
    assert [e.decoded("dtstart").isoformat() for e in events] == ["2031-05-05T09:00:00+00:00"]  # not the admin's
    # Someone else's subscription cannot be issued or revoked by a therapist.
    other = client.post(f"/api/v1/therapists/{seed.admin_id}/calendar-subscription", headers=seed.headers())
    assert other.status_code == 403
    # Re-issuing revokes the old link; revoking ends the new one.
    reissued = client.post(f"/api/v1/therapists/{seed.therapist_id}/calendar-subscription", headers=seed.headers())
    assert client.get(url).status_code == 404 and client.get(reissued.json()["url"]).status_code == 200
    status = client.get(f"/api/v1/therapists/{seed.therapist_id}/calendar-subscription", headers=seed.headers())
    assert status.json()["issued_at"] is not None and status.json()["url"] is None  # the secret is shown once
    revoked = client.delete(f"/api/v1/therapists/{seed.therapist_id}/calendar-subscription", headers=seed.headers())
    assert revoked.status_code == 204 and client.get(reissued.json()["url"]).status_code == 404
    assert client.get("/api/v1/calendar/" + "x" * 43 + ".ics").status_code == 404
