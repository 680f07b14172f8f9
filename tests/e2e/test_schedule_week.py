"""The schedule's clinic-local week in a real browser (issue 16 defect 7, §8): with the browser and the
clinic in Europe/Berlin, "Next week" and "Previous week" move by exactly one week (also across the DST
change), and a booking returns to its own week with the same patient selected. With the browser in
another zone (America/New_York), the page still shows and enters the clinic's wall-clock times. The week
is fetched in one request. A booking is dragged to another day and time, or onto a conflict (defect 10)."""

from __future__ import annotations

import contextlib
import os
import re
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from benchmarks.fault_harness import stop_robot_daemon
from tests.e2e.conftest import free_port

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

playwright_api = pytest.importorskip("playwright.sync_api")
expect = playwright_api.expect

ROOT = Path(__file__).resolve().parents[2]
USER = ("week-admin", "week-password-1")
CLINIC_ZONE = "Europe/Berlin"


@pytest.fixture(scope="module")
def clinic_service(tmp_path_factory: pytest.TempPathFactory, chromium_path: Path) -> Iterator[dict[str, object]]:
    """`ssp-rehab serve --no-robot` for a clinic in Europe/Berlin, with two patients and prescriptions."""
    data_dir = tmp_path_factory.mktemp("week-data")
    env = {**os.environ, "SSP_REHAB_TIMEZONE": CLINIC_ZONE, "SSP_REHAB_VIZ_ENABLED": "false"}
    cli = [sys.executable, "-m", "server.cli.main"]
    subprocess.run(
        [*cli, "create-user", "--username", USER[0], "--password", USER[1], "--role", "admin",
         "--data-dir", str(data_dir)],
        check=True, cwd=ROOT, env=env, capture_output=True,
    )  # fmt: skip
    port = free_port()
    log = (data_dir / "serve.log").open("w")
    process = subprocess.Popen(
        [*cli, "serve", "--no-robot", "--port", str(port), "--data-dir", str(data_dir)],
        cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120.0
        while True:
            assert process.poll() is None, (data_dir / "serve.log").read_text()[-2000:]
            try:
                if httpx.get(f"{base}/api/v1/health", timeout=1.0).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            assert time.monotonic() < deadline, "the service did not come up"
            time.sleep(0.3)
        token = httpx.post(f"{base}/api/v1/auth/login", json={"username": USER[0], "password": USER[1]}).json()
        headers = {"Authorization": f"Bearer {token['access_token']}"}
        patients = []
        for identifier, name in (("MRN-W1", "Anna Erste"), ("MRN-W2", "Bert Zweiter")):
            patient = httpx.post(
                f"{base}/api/v1/patients",
                json={"identifier": identifier, "name": name, "date_of_birth": "1950-02-03", "sex": "female",
                      "height_m": 1.65, "body_mass_kg": 60.0, "diagnosis": "stroke", "affected_side": "left"},
                headers=headers,
            ).json()  # fmt: skip
            segment = {
                "cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.5},
                "duration_s": 30,
            }
            httpx.post(
                f"{base}/api/v1/prescriptions",
                json={"patient_id": patient["id"], "name": f"Sway {identifier}", "segments": [segment]},
                headers=headers,
            ).raise_for_status()
            patients.append(patient)
        yield {"base_url": base, "headers": headers, "patients": patients}
    finally:
        process.terminate()
        process.wait(30)
        stop_robot_daemon(data_dir)  # serve leaves its daemon running, by design
        log.close()


@contextlib.contextmanager
def _logged_in(browser: Any, base: str, timezone_id: str) -> Iterator[Any]:
    """A logged-in page of the suite's Debian chromium with the browser's clock in `timezone_id`."""
    context = browser.new_context(viewport={"width": 1400, "height": 1000}, timezone_id=timezone_id, locale="en-GB")
    try:
        page = context.new_page()
        page.set_default_timeout(20_000)
        page.goto(f"{base}/#/login")
        page.get_by_label("Username").fill(USER[0])
        page.get_by_label("Password").fill(USER[1])
        page.get_by_role("button", name="Log in").click()
        expect(page.get_by_role("heading", name="Patients")).to_be_visible()
        yield page
    finally:
        context.close()


def _heading(page: object) -> object:
    return page.get_by_role("heading", name="Schedule: week of")  # type: ignore[attr-defined]


def test_week_navigation_and_booking_in_clinic_local_time(clinic_service: dict[str, object], browser: Any) -> None:
    base = str(clinic_service["base_url"])
    second_patient = clinic_service["patients"][1]  # type: ignore[index]
    with _logged_in(browser, base, CLINIC_ZONE) as page:
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        schedule_requests: list[str] = []
        page.on(
            "request",
            lambda request: (
                schedule_requests.append(request.url)
                if "/api/v1/sessions" in request.url or "/api/v1/schedule" in request.url
                else None
            ),
        )
        # The week before the spring change (clocks go forward on Sunday 30 March 2031).
        page.goto(f"{base}/#/schedule?week=2031-03-26")
        expect(_heading(page)).to_have_text("Schedule: week of 24 March 2031")
        page.get_by_role("button", name="Next week").click()
        expect(_heading(page)).to_have_text("Schedule: week of 31 March 2031")
        page.get_by_role("button", name="Next week").click()
        expect(_heading(page)).to_have_text("Schedule: week of 7 April 2031")
        page.get_by_role("button", name="Previous week").click()
        expect(_heading(page)).to_have_text("Schedule: week of 31 March 2031")
        page.get_by_role("button", name="Previous week").click()
        expect(_heading(page)).to_have_text("Schedule: week of 24 March 2031")
        page.get_by_role("button", name="Previous week").click()
        expect(_heading(page)).to_have_text("Schedule: week of 17 March 2031")

        # Book the second patient on Wednesday 2 April, 10:00 clinic time, from the week of 17 March.
        form = page.locator("form:has(h2:text('Book a session'))")
        form.get_by_label("Patient").select_option(str(second_patient["id"]))
        expect(form.get_by_label("Prescription").locator("option")).to_have_count(1)
        form.get_by_label("Start").fill("2031-04-02T10:00")
        form.get_by_label("Duration").fill("30")
        schedule_requests.clear()
        form.get_by_role("button", name="Book session").click()
        expect(_heading(page)).to_have_text("Schedule: week of 31 March 2031")
        day = page.get_by_role("region", name="Wednesday, 2 April 2031")
        expect(day.get_by_role("button", name="10:00–10:30")).to_be_visible()
        expect(day).to_contain_text("Bert Zweiter")
        expect(page.locator("form:has(h2:text('Book a session'))").get_by_label("Patient")).to_have_value(
            str(second_patient["id"])
        )
        week_loads = [url for url in schedule_requests if "/api/v1/schedule/week" in url]
        assert len(week_loads) == 1 and len(schedule_requests) == 2, schedule_requests  # the POST, one week GET

        # A time in the spring gap is refused next to the field, never shifted.
        form = page.locator("form:has(h2:text('Book a session'))")
        form.get_by_label("Start").fill("2031-03-30T02:30")
        form.get_by_role("button", name="Book session").click()
        expect(form).to_contain_text("does not exist in Europe/Berlin")

        # The therapist's own calendar link, for calendar apps that cannot log in.
        page.get_by_text("Calendar subscription").click()
        page.get_by_role("button", name="Get calendar link").click()
        link = page.get_by_label("Calendar subscription link")
        expect(link).to_have_value(re.compile(r"^http://127\.0\.0\.1:\d+/api/v1/calendar/[\w-]+\.ics$"))
        feed = httpx.get(link.input_value())  # no login
        assert feed.status_code == 200 and "DTSTART;TZID=Europe/Berlin:20310402T100000" in feed.text
        assert errors == []


def test_a_browser_in_another_zone_shows_and_enters_clinic_time(
    clinic_service: dict[str, object], browser: Any
) -> None:
    base = str(clinic_service["base_url"])
    first_patient = clinic_service["patients"][0]  # type: ignore[index]
    with _logged_in(browser, base, "America/New_York") as page:
        page.goto(f"{base}/#/schedule?week=2031-04-14&patient={first_patient['id']}")
        expect(_heading(page)).to_have_text("Schedule: week of 14 April 2031")
        form = page.locator("form:has(h2:text('Book a session'))")
        expect(form.get_by_label("Prescription").locator("option")).to_have_count(1)
        form.get_by_label("Start").fill("2031-04-15T09:15")
        form.get_by_role("button", name="Book session").click()
        day = page.get_by_role("region", name="Tuesday, 15 April 2031")
        expect(day.get_by_role("button", name="09:15–09:45")).to_be_visible()
        expect(page.get_by_text("Times are Europe/Berlin time")).to_be_visible()
    booked = httpx.get(
        f"{base}/api/v1/sessions",
        params={"patient_id": first_patient["id"]},
        headers=clinic_service["headers"],  # type: ignore[arg-type]
    ).json()
    assert [b["start"] for b in booked] == ["2031-04-15T07:15:00Z"]  # 09:15 in Berlin (CEST), not in New York


def _book(clinic_service: dict[str, object], patient: dict[str, Any], start_local: str) -> dict[str, Any]:
    base, headers = str(clinic_service["base_url"]), clinic_service["headers"]
    prescriptions = httpx.get(
        f"{base}/api/v1/prescriptions",
        params={"patient_id": patient["id"]},
        headers=headers,  # type: ignore[arg-type]
    ).json()
    created = httpx.post(
        f"{base}/api/v1/sessions",
        json={"patient_id": patient["id"], "prescription_id": prescriptions[0]["id"], "robot": "twin-drag",
              "start_local": start_local, "duration_s": 1800},
        headers=headers,  # type: ignore[arg-type]
    )  # fmt: skip
    assert created.status_code == 201, created.text
    return dict(created.json()[0])


def _session(clinic_service: dict[str, object], session_id: int) -> dict[str, Any]:
    base, headers = str(clinic_service["base_url"]), clinic_service["headers"]
    return dict(httpx.get(f"{base}/api/v1/sessions/{session_id}", headers=headers).json())  # type: ignore[arg-type]


def _slot_position(column: Any, clock: str) -> dict[str, float]:
    """Where in a day column the wall time `clock` is dropped: the column below its heading stands for
    06:00 to 21:45 in quarter hours (docs/ui.md)."""
    hours, minutes = (int(part) for part in clock.split(":"))
    step = (hours * 60 + minutes - 6 * 60) / 15
    geometry = column.evaluate(
        "c => ({height: c.getBoundingClientRect().height, top: c.querySelector('h3').offsetHeight,"
        " border: c.clientTop})"
    )
    usable = geometry["height"] - geometry["top"]
    # 63 quarter hours from 06:00 to 21:45; Playwright's position is from the padding box (inside the border).
    return {"x": 20.0, "y": geometry["top"] + usable * step / 63 - geometry["border"]}


def test_drag_a_booking_to_another_day_and_time_and_onto_a_conflict(
    clinic_service: dict[str, object], browser: Any
) -> None:
    """Issue 16 §8, defect 10: a scheduled booking is dragged to another day and time (clinic-local, same
    duration); dragged onto another booking of the same robot, the API's refusal is shown next to it and
    nothing moves. Alt + arrow keys move it by a quarter hour without a mouse."""
    base = str(clinic_service["base_url"])
    patients: list[dict[str, Any]] = clinic_service["patients"]  # type: ignore[assignment]
    first, second = patients
    moving = _book(clinic_service, first, "2031-05-05T10:00")  # Monday
    other = _book(clinic_service, second, "2031-05-06T11:00")  # Tuesday, same robot
    with _logged_in(browser, base, "America/New_York") as page:  # the browser's zone must not matter
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(f"{base}/#/schedule?week=2031-05-05")
        expect(_heading(page)).to_have_text("Schedule: week of 5 May 2031")
        monday = page.get_by_role("region", name="Monday, 5 May 2031")
        thursday = page.get_by_role("region", name="Thursday, 8 May 2031")
        card = monday.get_by_role("button", name="10:00–10:30")
        card.drag_to(thursday, target_position=_slot_position(thursday, "14:15"))
        expect(thursday.get_by_role("button", name="14:15–14:45")).to_be_visible()
        expect(monday.locator(".booking")).to_have_count(0)
        moved = _session(clinic_service, moving["id"])
        assert moved["start_local"] == "2031-05-08T14:15:00+02:00" and moved["duration_s"] == 1800, moved

        # Onto the other booking of the same robot: refused in place, in words, and nothing moves.
        tuesday = page.get_by_role("region", name="Tuesday, 6 May 2031")
        card = thursday.get_by_role("button", name="14:15–14:45")
        card.drag_to(tuesday.get_by_role("button", name="11:00–11:30"))
        refusal = thursday.get_by_role("alert")
        expect(refusal).to_contain_text("Could not move to Tue 6 May 11:00")
        expect(refusal).to_contain_text(
            f"The robot is already booked from 2031-05-06 11:00 to 11:30 (session {other['id']})"
        )
        expect(card).to_be_visible()
        assert _session(clinic_service, moving["id"])["start_local"] == "2031-05-08T14:15:00+02:00"
        assert _session(clinic_service, other["id"])["start_local"] == "2031-05-06T11:00:00+02:00"

        # The keyboard equivalent: Alt + ↓ is a quarter hour later.
        card.focus()
        page.keyboard.press("Alt+ArrowDown")
        expect(thursday.get_by_role("button", name="14:30–15:00")).to_be_visible()
        assert _session(clinic_service, moving["id"])["start_local"] == "2031-05-08T14:30:00+02:00"

        # Only scheduled bookings can be dragged: a cancelled one stays put.
        cancelled = httpx.patch(
            f"{base}/api/v1/sessions/{other['id']}", json={"status": "cancelled"},
            headers=clinic_service["headers"],  # type: ignore[arg-type]
        )  # fmt: skip
        assert cancelled.status_code == 200, cancelled.text
        page.reload()
        expect(tuesday.get_by_role("button", name="11:00–11:30")).not_to_have_attribute("draggable", "true")
        expect(thursday.get_by_role("button", name="14:30–15:00")).to_have_attribute("draggable", "true")
        assert errors == []


def test_a_move_into_the_spring_gap_is_refused_next_to_the_booking(
    clinic_service: dict[str, object], browser: Any
) -> None:
    """Moved a day later from Saturday 02:30 into Sunday 30 March 2031, 02:30 (Europe/Berlin's spring gap):
    the 422 is shown next to the booking in words, and the booking keeps its time."""
    base = str(clinic_service["base_url"])
    patients: list[dict[str, Any]] = clinic_service["patients"]  # type: ignore[assignment]
    booking = _book(clinic_service, patients[0], "2031-03-29T02:30")
    with _logged_in(browser, base, CLINIC_ZONE) as page:
        page.goto(f"{base}/#/schedule?week=2031-03-24")
        expect(_heading(page)).to_have_text("Schedule: week of 24 March 2031")
        saturday = page.get_by_role("region", name="Saturday, 29 March 2031")
        saturday.get_by_role("button", name="02:30–03:00").focus()
        page.keyboard.press("Alt+ArrowRight")
        refusal = saturday.get_by_role("alert")
        expect(refusal).to_contain_text("Could not move to Sun 30 Mar 02:30")
        expect(refusal).to_contain_text("does not exist in Europe/Berlin")
        expect(page.get_by_role("region", name="Sunday, 30 March 2031").locator(".booking")).to_have_count(0)
    assert _session(clinic_service, booking["id"])["start_local"] == "2031-03-29T02:30:00+01:00"
