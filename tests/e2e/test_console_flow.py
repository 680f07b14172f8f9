"""The clinician's flow through the web console in a real browser (issue 7 §4): log in → create a patient →
create a prescription → schedule a session → start a simulated session → see the 3D view and the charts
update → emergency stop → the session shows as stopped with the event → export the log.
Screenshots go to artifacts/e2e/ (see the README)."""

from __future__ import annotations

import datetime as dt
import re
from typing import Any

import pytest

from tests.e2e.conftest import ADMIN, ARTIFACTS

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

playwright_api = pytest.importorskip("playwright.sync_api")
expect = playwright_api.expect


def test_clinician_flow(console_service: dict[str, object], browser: Any) -> None:
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    base_url = str(console_service["base_url"])
    shots = iter(range(1, 100))

    def shot(page, name: str) -> None:
        page.screenshot(path=str(ARTIFACTS / f"{next(shots):02d}-{name}.png"), full_page=True)

    context = browser.new_context(viewport={"width": 1600, "height": 1000}, accept_downloads=True)
    page = context.new_page()
    page.set_default_timeout(30_000)
    console_errors: list[str] = []
    page.on("pageerror", lambda error: console_errors.append(str(error)))

    try:
        # 1. Log in.
        page.goto(f"{base_url}/#/login")
        expect(page.locator("#estop")).to_be_visible()  # the emergency stop is on every page, the login too
        page.get_by_label("Username").fill(ADMIN[0])
        page.get_by_label("Password").fill(ADMIN[1])
        shot(page, "login")
        page.get_by_role("button", name="Log in").click()
        expect(page.get_by_role("heading", name="Patients")).to_be_visible()

        # 2. Create a patient (an invalid height first: the API's message appears next to the field).
        page.get_by_role("button", name="New patient").click()
        page.get_by_label("Record number").fill("MRN-E2E-1")
        page.get_by_label("Name").fill("Ada Example")
        page.get_by_label("Date of birth").fill("1958-05-17")
        page.get_by_label("Sex").select_option("female")
        page.get_by_label("Height").fill("300")
        page.get_by_label("Body mass").fill("64")
        page.get_by_label("Diagnosis").fill("stroke")
        page.get_by_role("button", name="Create patient").click()
        height_error = page.locator(".field:has(#" + page.get_by_label("Height").get_attribute("id") + ") .field-error")
        expect(height_error).to_contain_text("250 cm")  # the unit on screen, not the API's metres
        shot(page, "patient-validation")
        page.get_by_label("Height").fill("168")
        page.get_by_role("button", name="Create patient").click()
        expect(page.get_by_role("heading", name="Ada Example")).to_be_visible()
        shot(page, "patient-profile")

        # 3. Create a prescription, with a preview of the motion first.
        page.get_by_role("link", name="New prescription").click()
        page.get_by_label("Prescription name").fill("Lateral sway, week 1")
        page.get_by_label("Duration").fill("40")
        page.get_by_label("Amplitude").fill("0.6")
        page.get_by_label("Frequency").fill("0.5")
        page.get_by_role("button", name="Preview motion").click()
        expect(page.locator(".verdict")).to_contain_text("accepts", timeout=120_000)
        # Position, angles, perceived acceleration at the head, slider travel, tilt rate against the threshold.
        expect(page.locator("#main .chart")).to_have_count(5)
        shot(page, "prescription-preview")
        page.get_by_role("button", name="Save prescription").click()
        expect(page.get_by_role("heading", name="Prescription: Lateral sway, week 1 (v1)")).to_be_visible()

        # 4. Schedule a session, in the week view.
        page.get_by_role("link", name="Schedule").click()
        start = (dt.datetime.now() + dt.timedelta(minutes=30)).replace(second=0, microsecond=0)
        page.get_by_label("Start").fill(start.strftime("%Y-%m-%dT%H:%M"))
        page.get_by_label("Duration").fill("30")
        page.get_by_role("button", name="Book session").click()
        booking = page.locator("button.booking").filter(has_text="Ada Example").first
        expect(booking).to_be_visible()
        shot(page, "schedule-week")
        booking.click()
        page.get_by_role("link", name="Open session console").click()
        expect(page.get_by_role("heading", name="Session console: Ada Example")).to_be_visible()

        # 5. Start the simulated session: a confirmation with a checklist comes before any motion. An earlier
        # test's stop on this shared robot may wait for an acknowledgement first, as the console asks.
        page.wait_for_function(
            "() => !document.querySelector('#start-button').disabled"
            " || document.querySelector('#acknowledge-button')?.offsetParent != null",
            timeout=30_000,
        )
        if page.locator("#acknowledge-button").is_visible():
            page.locator("#acknowledge-button").click()
            for box in page.locator("#confirm-dialog").get_by_role("checkbox").all():
                box.check()
            page.locator("#confirm-ok").click()
            expect(page.locator("#start-button")).to_be_enabled(timeout=15_000)
        # The console wires Start once the page's data has loaded: click until its dialog answers.
        dialog = page.locator("#confirm-dialog")
        for _ in range(120):
            page.locator("#start-button").click()
            if dialog.is_visible():
                break
            page.wait_for_timeout(500)
        expect(dialog).to_be_visible()
        expect(page.locator("#confirm-ok")).to_be_disabled()
        for box in dialog.get_by_role("checkbox").all():
            box.check()
        shot(page, "start-confirmation")
        page.locator("#confirm-ok").click()
        expect(page.locator("#run-state")).to_have_attribute("data-state", "running", timeout=120_000)

        # 6. The 3D view loads and follows the robot; the live charts fill.
        frame = page.frame_locator("#viz-frame")
        expect(frame.locator("canvas").first).to_be_visible(timeout=60_000)
        viz_status = page.locator("#viz-status")
        expect(viz_status).to_have_attribute("data-mode", "live", timeout=30_000)
        first_frames = _frames_shown(page)
        viz_before = page.locator("#viz-frame").screenshot()
        page.wait_for_timeout(1500)
        viz_after = page.locator("#viz-frame").screenshot()
        assert _frames_shown(page) > first_frames, "the 3D view did not update while the robot moved"
        assert viz_before != viz_after, "the 3D view's picture did not change while the robot moved"
        chart_samples = _live_samples(page)
        page.wait_for_timeout(500)
        assert _live_samples(page) > chart_samples > 0, "the live charts did not receive telemetry"
        shot(page, "live-console")

        # 7. Emergency stop, with its key (Escape) from the page: one call, no confirmation.
        # The page's stop goes to the robot's stop listener (or /api/v1/estop when it cannot reach it).
        with page.expect_response(lambda r: r.request.method == "POST" and r.url.endswith("/estop")) as estop:
            page.keyboard.press("Escape")
        assert estop.value.status == 200
        expect(page.locator(".banner.error").filter(has_text="EMERGENCY STOP sent")).to_be_visible()

        # 8. The session shows as stopped (emergency stop), with the event recorded.
        expect(page.locator("#run-state")).to_have_attribute("data-state", "emergency_stop", timeout=30_000)
        expect(page.locator('#runs tr[data-kind="emergency_stop"]').first).to_be_visible(timeout=30_000)
        expect(page.locator("#robot-status")).to_contain_text("E-STOP", timeout=15_000)
        # The latched stop shows in the controls too: nothing can be started until a reset.
        expect(page.locator("#start-button")).to_be_disabled(timeout=15_000)
        shot(page, "after-estop")

        # 9. Export the log: the download succeeds and is not empty.
        page.wait_for_timeout(3000)  # the recorder writes the run's tail (2 s) after the stop
        # An export is a job with a progress bar; the file downloads once it is built (issue 20, build 7).
        with page.expect_download(timeout=180_000) as download_info:
            page.get_by_role("button", name=re.compile(r"^Export run \d+ log$")).first.click()
        download = download_info.value
        assert download.failure() is None
        saved = ARTIFACTS / download.suggested_filename
        download.save_as(saved)
        assert saved.stat().st_size > 0
        assert download.suggested_filename.endswith(".zip")

        # The replay of the finished run plays in the same 3D view.
        page.get_by_role("button", name="Replay run").first.click()
        expect(viz_status).to_have_attribute("data-mode", "replay", timeout=10_000)
        # The charts show the replayed run, not the live robot (issue 16, defect 11).
        expect(page.locator("#charts-title")).to_contain_text("replay")
        expect(page.locator("#live-charts")).to_have_attribute(
            "data-replay-samples", re.compile(r"^[1-9]"), timeout=15_000
        )
        live_frames = _live_samples(page)
        page.wait_for_timeout(2000)  # live frames keep coming during the replay: none of them is drawn
        drawn = page.locator("#live-charts").evaluate(
            "el => [Number(el.dataset.plotted), Number(el.dataset.replaySamples)]"
        )
        assert _live_samples(page) > live_frames and drawn[0] == drawn[1], (
            f"the replay's charts drew {drawn[0]} samples, of which {drawn[1]} from the replayed run"
        )
        shot(page, "replay")
        page.get_by_role("link", name="Session history").click()
        expect(page.get_by_role("heading", name="Session history")).to_be_visible()
        shot(page, "history")

        # The balance trend: one measure and one unit per chart, by date (issue 16).
        page.get_by_role("link", name="Patients").click()
        page.get_by_role("row").filter(has_text="Ada Example").get_by_role("link", name="Open profile").click()
        # This run lasted seconds: too short for sway measures (at least 20 s, issue 22 §6), and the page says so.
        expect(page.locator("#balance-not-measured")).to_contain_text("at least 20 s")
        expect(page.locator("#balance-trend .chart")).to_have_count(0)
        expect(page.locator("#main")).not_to_contain_text("null")
        shot(page, "balance-trend")
    except Exception:
        shot(page, "failure")  # the page as it was when the flow broke
        raise
    assert not console_errors, f"JavaScript errors in the page: {console_errors}"
    context.close()


def _frames_shown(page) -> int:
    return int(page.locator("#viz-status").get_attribute("data-frames") or 0)


def _live_samples(page) -> int:
    return int(page.locator("#live-charts").get_attribute("data-samples") or 0)
