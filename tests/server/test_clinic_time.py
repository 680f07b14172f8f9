"""Clinic-local time (issue 15 §1): recurring series keep their wall-clock time across daylight-saving
changes, DST gap and overlap times are refused naming the field, answers carry UTC and local times, the
iCalendar feed carries TZID and VTIMEZONE; the week of the schedule is a clinic-local week (issue 16 §8)."""

from __future__ import annotations

import datetime as dt
from collections.abc import Iterator
from zoneinfo import ZoneInfo

import pytest
from fastapi.testclient import TestClient
from icalendar import Calendar

from server.app import create_app
from server.db import Database
from server.settings import Settings
from tests.server.conftest import Seed, book, create_patient, create_prescription


@pytest.fixture(params=["Europe/Berlin", "America/New_York"])
def zone_name(request: pytest.FixtureRequest) -> str:
    return str(request.param)


def clinic_client(settings: Settings, database: Database, zone: str) -> TestClient:
    return TestClient(create_app(settings.model_copy(update={"timezone": zone}), database=database, worker=None))


@pytest.fixture
def berlin(settings: Settings, database: Database) -> Iterator[TestClient]:
    with clinic_client(settings, database, "Europe/Berlin") as client:
        yield client


@pytest.fixture
def new_york(settings: Settings, database: Database) -> Iterator[TestClient]:
    with clinic_client(settings, database, "America/New_York") as client:
        yield client


def patient_and_prescription(client: TestClient, seed: Seed, identifier: str = "MRN-TZ") -> tuple[int, int]:
    patient_id = create_patient(client, seed.headers(), identifier=identifier)
    return patient_id, create_prescription(client, seed.headers(), patient_id)


def aware(local: str, zone: str) -> str:
    """A local wall time as the API takes it: ISO 8601 with the zone's offset at that time."""
    return dt.datetime.fromisoformat(local).replace(tzinfo=ZoneInfo(zone)).isoformat()


# (zone, frequency, first local start, count): each series crosses a spring or an autumn change.
SERIES_ACROSS_CHANGES = [
    ("Europe/Berlin", "weekly", "2031-03-18T09:00", 3),  # clocks go forward on 2031-03-30
    ("Europe/Berlin", "daily", "2031-03-28T09:00", 4),
    ("Europe/Berlin", "weekly", "2031-10-14T09:00", 3),  # clocks go back on 2031-10-26
    ("Europe/Berlin", "daily", "2031-10-24T18:30", 4),
    ("America/New_York", "weekly", "2031-03-04T09:00", 3),  # forward on 2031-03-09
    ("America/New_York", "daily", "2031-03-07T07:15", 4),
    ("America/New_York", "weekly", "2031-10-28T09:00", 3),  # back on 2031-11-02
    ("America/New_York", "daily", "2031-10-31T16:00", 4),
]


@pytest.mark.parametrize(("zone", "frequency", "first_local", "count"), SERIES_ACROSS_CHANGES)
def test_a_series_keeps_its_local_time_across_a_daylight_saving_change(
    settings: Settings, database: Database, seed: Seed, zone: str, frequency: str, first_local: str, count: int
) -> None:
    with clinic_client(settings, database, zone) as client:
        patient_id, prescription_id = patient_and_prescription(client, seed)
        response = book(
            client,
            seed.headers(),
            patient_id=patient_id,
            prescription_id=prescription_id,
            start=aware(first_local, zone),
            recurrence={"frequency": frequency, "interval": 1, "count": count},
        )
        assert response.status_code == 201, response.text
        bookings = response.json()
    wall_time = dt.time.fromisoformat(first_local[11:])
    local_starts = [dt.datetime.fromisoformat(b["start"]).astimezone(ZoneInfo(zone)) for b in bookings]
    assert [s.time() for s in local_starts] == [wall_time] * count, local_starts
    step = dt.timedelta(days=7 if frequency == "weekly" else 1)
    first_day = dt.date.fromisoformat(first_local[:10])
    assert [s.date() for s in local_starts] == [first_day + k * step for k in range(count)]
    # Across the change the UTC offset differs, so the UTC times do not keep one step.
    assert len({s.utcoffset() for s in local_starts}) == 2
    # The answer reports both: UTC, and the clinic-local time with its offset.
    assert all(b["start"].endswith("Z") for b in bookings)
    assert [dt.datetime.fromisoformat(b["start_local"]) for b in bookings] == local_starts
    assert {b["timezone"] for b in bookings} == {zone}


def test_an_occurrence_in_the_spring_gap_is_refused_naming_it(berlin: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_and_prescription(berlin, seed)
    response = book(
        berlin,
        seed.headers(),
        patient_id=patient_id,
        prescription_id=prescription_id,
        start="2031-03-23T02:30:00+01:00",
        recurrence={"frequency": "weekly", "interval": 1, "count": 3},
    )
    assert response.status_code == 422, response.text
    (error,) = response.json()["detail"]
    assert error["loc"] == ["body", "recurrence"]
    assert "occurrence 2 of 3" in error["msg"] and "2031-03-30 02:30" in error["msg"]
    assert "does not exist in Europe/Berlin" in error["msg"]
    assert berlin.get("/api/v1/sessions", headers=seed.headers()).json() == []  # nothing half-written


def test_a_local_start_in_the_gap_is_refused_never_shifted(berlin: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_and_prescription(berlin, seed)
    body = {"patient_id": patient_id, "prescription_id": prescription_id, "robot": "twin-1", "duration_s": 1800}
    gap = berlin.post("/api/v1/sessions", json={**body, "start_local": "2031-03-30T02:30"}, headers=seed.headers())
    assert gap.status_code == 422, gap.text
    (error,) = gap.json()["detail"]
    assert error["loc"] == ["body", "start_local"] and "does not exist in Europe/Berlin" in error["msg"]
    fine = berlin.post("/api/v1/sessions", json={**body, "start_local": "2031-03-30T03:30"}, headers=seed.headers())
    assert fine.status_code == 201, fine.text
    assert fine.json()[0]["start"] == "2031-03-30T01:30:00Z"
    assert fine.json()[0]["start_local"] == "2031-03-30T03:30:00+02:00"
    both = berlin.post(
        "/api/v1/sessions",
        json={**body, "start_local": "2031-04-01T10:00", "start": "2031-04-01T08:00:00Z"},
        headers=seed.headers(),
    )
    assert both.status_code == 422 and "exactly one of start and start_local" in both.text


@pytest.mark.parametrize("start_field", ["start", "start_local", "recurrence"])
def test_an_ambiguous_time_in_the_autumn_overlap_is_refused(new_york: TestClient, seed: Seed, start_field: str) -> None:
    patient_id, prescription_id = patient_and_prescription(new_york, seed)
    body: dict[str, object] = {
        "patient_id": patient_id,
        "prescription_id": prescription_id,
        "robot": "twin-1",
        "duration_s": 1800,
    }
    if start_field == "start":  # the second 01:30 of 2031-11-02, given with its offset: still ambiguous on a wall
        body["start"] = "2031-11-02T01:30:00-05:00"
    elif start_field == "start_local":
        body["start_local"] = "2031-11-02T01:30"
    else:
        body["start"] = "2031-11-01T01:30:00-04:00"
        body["recurrence"] = {"frequency": "daily", "interval": 1, "count": 2}
    response = new_york.post("/api/v1/sessions", json=body, headers=seed.headers())
    assert response.status_code == 422, response.text
    (error,) = response.json()["detail"]
    assert error["loc"] == ["body", start_field]
    assert "2031-11-02 01:30" in error["msg"] and "ambiguous in America/New_York" in error["msg"]


def test_moving_a_booking_to_a_gap_time_is_refused(berlin: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_and_prescription(berlin, seed)
    created = book(
        berlin,
        seed.headers(),
        patient_id=patient_id,
        prescription_id=prescription_id,
        start="2031-03-28T10:00:00+01:00",
    )
    booking_id = created.json()[0]["id"]
    moved = berlin.patch(
        f"/api/v1/sessions/{booking_id}", json={"start_local": "2031-03-30T02:15"}, headers=seed.headers()
    )
    assert moved.status_code == 422 and moved.json()["detail"][0]["loc"] == ["body", "start_local"]
    assert berlin.get(f"/api/v1/sessions/{booking_id}", headers=seed.headers()).json()["start"] == (
        "2031-03-28T09:00:00Z"
    )


def test_the_calendar_feed_carries_tzid_and_vtimezone(berlin: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_and_prescription(berlin, seed)
    book(
        berlin,
        seed.headers(),
        patient_id=patient_id,
        prescription_id=prescription_id,
        start="2031-03-25T09:00:00+01:00",
        recurrence={"frequency": "weekly", "interval": 1, "count": 2},
    )
    feed = berlin.get(f"/api/v1/therapists/{seed.therapist_id}/calendar.ics", headers=seed.headers())
    assert feed.status_code == 200
    calendar = Calendar.from_ical(feed.content)
    assert [tz["tzid"] for tz in calendar.walk("VTIMEZONE")] == ["Europe/Berlin"]
    assert "DTSTART;TZID=Europe/Berlin:20310325T090000" in feed.text
    assert "DTSTART;TZID=Europe/Berlin:20310401T090000" in feed.text


def test_the_clinic_time_zone_setting_is_checked() -> None:
    with pytest.raises(ValueError, match="timezone"):
        Settings(_env_file=None, timezone="Europe/Atlantis")  # type: ignore[call-arg]
    assert Settings(_env_file=None, timezone="America/New_York").clinic_zone() == ZoneInfo("America/New_York")  # type: ignore[call-arg]
    assert Settings(_env_file=None).timezone  # type: ignore[call-arg]  # default: the machine's zone


def test_the_week_is_a_clinic_local_week_fetched_in_one_request(berlin: TestClient, seed: Seed) -> None:
    patient_id, prescription_id = patient_and_prescription(berlin, seed)
    # Monday 00:30 just after the spring week (167 h long): a 7 x 24 h window from Monday 00:00 would hold it.
    for start in ("2031-03-24T00:00:00+01:00", "2031-03-30T23:00:00+02:00", "2031-03-31T00:30:00+02:00"):
        assert (
            book(
                berlin, seed.headers(), patient_id=patient_id, prescription_id=prescription_id, start=start
            ).status_code
            == 201
        )
    week = berlin.get("/api/v1/schedule/week", params={"day": "2031-03-27"}, headers=seed.headers())
    assert week.status_code == 200, week.text
    answer = week.json()
    assert answer["timezone"] == "Europe/Berlin"
    assert answer["start_local"] == "2031-03-24T00:00:00+01:00" and answer["end_local"] == "2031-03-31T00:00:00+02:00"
    assert answer["previous_week"] == "2031-03-17" and answer["next_week"] == "2031-03-31"
    assert [b["start_local"] for b in answer["bookings"]] == ["2031-03-24T00:00:00+01:00", "2031-03-30T23:00:00+02:00"]
    assert {b["patient_name"] for b in answer["bookings"]} == {"Greta Testperson"}
    assert all(b["run_count"] == 0 and b["last_run_outcome"] is None for b in answer["bookings"])
    following = berlin.get("/api/v1/schedule/week", params={"day": "2031-03-31"}, headers=seed.headers()).json()
    assert [b["start_local"] for b in following["bookings"]] == ["2031-03-31T00:30:00+02:00"]
