"""Issue 16's console defects, each reproduced in a real browser (Debian's chromium through Playwright):
the emergency stop at every width, faults and falls in sight with an acknowledgement before a restart,
stale and broken pages, the clinician's language, and the offline API docs. Screenshots of failures go
to artifacts/e2e/."""

from __future__ import annotations

import datetime as dt
import json
import re
from typing import Any

import httpx
import pytest

from tests.e2e.conftest import THERAPIST, VIEWPORTS, field_error, fill_patient, turn_engineering_on

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

playwright_api = pytest.importorskip("playwright.sync_api")
expect = playwright_api.expect

# --- defect 1: the emergency stop, whole and first, at every width --------------------------------------------


ESTOP_GEOMETRY_JS = """() => {
  const button = document.getElementById('estop');
  const box = button.getBoundingClientRect();
  const label = button.querySelector('.estop-label');
  const others = [...document.querySelector('.topbar').children]
    .filter((el) => el !== button && el.getClientRects().length)
    .map((el) => el.getBoundingClientRect());
  const hit = document.elementFromPoint(box.left + box.width / 2, box.top + box.height / 2);
  return {
    left: box.left, top: box.top, right: box.right, bottom: box.bottom,
    width: innerWidth, height: innerHeight, pageWidth: document.documentElement.scrollWidth,
    labelClipped: label.scrollWidth > label.clientWidth + 1,
    firstInRow: others.every((o) => o.top >= box.bottom - 1 || box.left <= o.left + 1),
    covered: !(hit && button.contains(hit)),
  };
}"""


def _assert_estop_whole(page: Any, where: str) -> None:
    g = page.evaluate(ESTOP_GEOMETRY_JS)
    size = f"{g['width']}x{g['height']}"
    assert g["left"] >= 0 and g["top"] >= 0, f"{where} at {size}: the emergency stop starts off-screen ({g})"
    assert g["right"] <= g["width"] and g["bottom"] <= g["height"], (
        f"{where} at {size}: the emergency stop is cut off (right edge {g['right']:.0f} px) ({g})"
    )
    assert not g["labelClipped"], f"{where} at {size}: the label 'EMERGENCY STOP' is clipped"
    assert g["firstInRow"], f"{where} at {size}: the emergency stop is not first in the top bar"
    assert not g["covered"], f"{where} at {size}: something covers the emergency stop"
    assert g["pageWidth"] <= g["width"], f"{where} at {size}: the page scrolls sideways ({g['pageWidth']} px)"


@pytest.mark.parametrize("viewport", VIEWPORTS, ids=[f"{w}x{h}" for w, h in VIEWPORTS])
def test_estop_whole_and_first_on_every_page(console: Any, clinic: dict[str, Any], viewport: tuple[int, int]) -> None:
    session = console(user=THERAPIST, viewport=viewport)
    page = session.go("#/login")
    expect(page.locator("#estop")).to_be_visible()
    _assert_estop_whole(page, "login")
    session.login()
    patient, prescription = clinic["patient"]["id"], clinic["prescription"]["id"]
    pages = {
        "patients": ("#/patients", "Patients"),
        "new patient": ("#/patients/new", "New patient"),
        "patient profile": (f"#/patients/{patient}", "Jürgen Äbischer"),
        "new prescription": (f"#/prescriptions/new?patient={patient}", "New prescription"),
        "prescription": (f"#/prescriptions/{prescription}", "Prescription: Sway basics"),
        "schedule": ("#/schedule", "Schedule"),
        "session console": (f"#/session/{clinic['booking']['id']}", "Session console"),
        "history": ("#/history", "Session history"),
    }
    for where, (route, heading) in pages.items():
        session.go(route)
        expect(page.get_by_role("heading", name=heading).first).to_be_visible()
        _assert_estop_whole(page, where)
    # The emergency stop is the first stop of the keyboard too: first focusable element, no positive tabindex.
    first_focusable = page.evaluate("""() => {
      const focusable = [...document.querySelectorAll('a[href], button, input, select, textarea, [tabindex]')]
        .filter((el) => el.tabIndex >= 0 && el.getClientRects().length);
      return [focusable[0].id, focusable.filter((el) => el.tabIndex > 0).length];
    }""")
    assert first_focusable == ["estop", 0], first_focusable


# --- defect 2: faults, falls and watchdog stops in sight; a restart after a fall needs an acknowledgement -------


# The stops of defect 2 (a watchdog stop, a detected fall): the top bar's status, a banner's name and plain reason.
ABNORMAL_STOPS = [("watchdog", "watchdog", "lost contact"), ("fall", "fall", "a fall was detected")]


@pytest.mark.parametrize(("stop_reason", "named", "reason"), ABNORMAL_STOPS, ids=[s[0] for s in ABNORMAL_STOPS])
def test_watchdog_stop_shows_as_a_fault_with_reason_and_next_step(
    console: Any, stop_reason: str, named: str, reason: str
) -> None:
    session = console()
    page = session.login()
    stopped = {"state": "stopped", "stop_reason": stop_reason, "estop_latched": False, "hal_state": "ready"}
    page.route("**/api/v1/robot/state", lambda route: route.fulfill(json=stopped))
    status = page.locator("#robot-status")
    expect(status).to_have_class(re.compile(r"\bbad\b"), timeout=10_000)
    expect(status).not_to_have_class(re.compile(r"\bok\b"))
    expect(status).to_contain_text(named.upper())  # not a calm "Robot: STOPPED"
    alert = page.locator(".banner.error, .banner.fall").filter(has_text=named)
    expect(alert).to_be_visible()
    expect(alert).to_contain_text(reason)  # the plain reason
    expect(alert).to_contain_text("Next step")
    # Back to a normal idle robot: the alert goes away and the status is calm again.
    page.unroute("**/api/v1/robot/state")
    expect(status).to_have_class(re.compile(r"\bok\b"), timeout=10_000)
    expect(alert).to_have_count(0)


def test_a_robot_warming_up_shows_as_starting_and_a_failed_one_offers_a_retry(console: Any) -> None:
    """Issue 15 §2: while the robot daemon warms up the console says "starting" with its progress, never
    "offline"; a daemon that failed shows its reason and a Retry."""
    session = console()
    page = session.login()
    health = {"status": "ok", "robot_connected": False}
    not_ready = {"detail": "robot 'twin-1' is not ready"}
    page.route("**/api/v1/robot/state", lambda route: route.fulfill(status=503, json=not_ready))
    starting = {**health, "robot": {"state": "starting", "reason": "compiling the real-time kernels (12 s so far)"}}
    page.route("**/api/v1/health", lambda route: route.fulfill(json=starting))
    status = page.locator("#robot-status")
    expect(status).to_have_text("Robot: STARTING", timeout=10_000)
    expect(page.locator(".banner.warning")).to_contain_text("compiling the real-time kernels (12 s so far)")
    expect(page.get_by_text("Robot: OFFLINE")).to_have_count(0)
    page.unroute("**/api/v1/health")
    failed = {**health, "robot": {"state": "fault", "reason": "the real-time worker exited (exit code 1)"}}
    page.route("**/api/v1/health", lambda route: route.fulfill(json=failed))
    expect(status).to_have_text("Robot: FAULT", timeout=10_000)
    alert = page.locator(".banner.error").filter(has_text="exit code 1")
    expect(alert.get_by_role("button", name="Retry")).to_be_visible()
    page.unroute("**/api/v1/health")
    page.unroute("**/api/v1/robot/state")
    alert.get_by_role("button", name="Retry").click()  # checks again at once: the real robot is there
    expect(status).not_to_have_text(re.compile("FAULT|STARTING"), timeout=10_000)


def test_a_robot_without_force_plates_shows_fall_detection_off(console: Any, clinic: dict[str, Any]) -> None:
    """A backend that reads no force plates or harness load cell (the CANopen drives) runs the session with no
    fall detector: the session page says so in orange. The robot's real telemetry, with the robot's flag set
    as that backend sets it; on this (kinematic) robot, which reads its plates, nothing is said."""
    session = console()
    page = session.login()
    plateless = {"on": False}

    def relay(ws: Any) -> None:
        server = ws.connect_to_server()

        def forward(message: str | bytes) -> None:
            frame = json.loads(message)
            if plateless["on"] and frame.get("state"):
                frame["state"]["fall_detection_unavailable"] = True
            ws.send(json.dumps(frame))

        server.on_message(forward)

    page.route_web_socket(re.compile(r"/telemetry$"), relay)
    session.go(f"#/session/{clinic['booking']['id']}")
    expect(page.get_by_role("heading", name="Session console")).to_be_visible()
    health = page.locator("#health")
    expect(health.locator(".metric").filter(has_text="Harness load")).to_be_visible(timeout=15_000)
    expect(health.locator(".metric").filter(has_text="Fall detection")).to_have_count(0)
    plateless["on"] = True
    off = health.locator(".metric").filter(has_text="Fall detection")
    expect(off).to_contain_text("off (no force plates on this robot)", timeout=15_000)
    expect(off).to_have_class(re.compile(r"\bwarn\b"))


def test_restart_after_a_fall_needs_an_acknowledgement(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    session.go(f"#/session/{clinic['fall_booking']['id']}")
    expect(page.get_by_role("heading", name="Session console")).to_be_visible()
    expect(page.locator("#run-state")).to_have_attribute("data-state", "fall")
    start = page.locator("#start-button")
    expect(start).to_be_disabled()
    acknowledge = page.locator("#acknowledge-button")
    expect(acknowledge).to_be_visible()
    expect(page.locator("#acknowledge-panel")).to_contain_text("fall")
    acknowledge.click()
    dialog = page.locator("#confirm-dialog")
    expect(dialog).to_be_visible()
    expect(page.locator("#confirm-ok")).to_be_disabled()  # the checks come first
    for box in dialog.get_by_role("checkbox").all():
        box.check()
    page.locator("#confirm-ok").click()
    expect(start).to_be_enabled(timeout=15_000)
    # The acknowledgement is an event of the run, with who made it.
    events = httpx.get(f"{clinic['api']}/runs/{clinic['fall_run_id']}/events",
                       headers={"Authorization": f"Bearer {clinic['admin_token']}"}).json()  # fmt: skip
    acknowledged = [e for e in events if e["kind"] == "acknowledged"]
    assert len(acknowledged) == 1 and acknowledged[0]["user_id"] is not None, events
    assert not session.errors, session.errors


# --- defect 3 / build 2: banners and charts of a live run give the time into the run, not the worker's uptime ----


def _seed_running_run(database_url: str, booking: dict[str, Any], start_tick_time_s: float) -> int:
    """A run in progress (as the recorder writes it at a start), so the session console follows it live."""
    from sqlalchemy import select

    from server.db import Database, create_database_engine, load_models
    from server.prescriptions.models import PrescriptionVersion
    from server.robotd.models import SessionEvent, SessionRun

    load_models()
    engine = create_database_engine(database_url)
    try:
        with Database(engine).session() as session:
            version = session.scalars(select(PrescriptionVersion.id).where(
                PrescriptionVersion.prescription_id == booking["prescription_id"])).first()  # fmt: skip
            run = SessionRun(scheduled_session_id=booking["id"], prescription_version_id=version,
                             robot=booking["robot"], state="running")  # fmt: skip
            session.add(run)
            session.flush()
            session.add(SessionEvent(run_id=run.id, kind="start", tick=0, tick_time_s=start_tick_time_s,
                                     detector="console", details={}))  # fmt: skip
            session.commit()
            return int(run.id)
    finally:
        engine.dispose()


def _end_run(database_url: str, run_id: int) -> None:
    from server.db import Database, create_database_engine, load_models
    from server.robotd.models import SessionRun

    load_models()
    engine = create_database_engine(database_url)
    try:
        with Database(engine).session() as session:
            run = session.get(SessionRun, run_id)
            run.state, run.outcome, run.ended_at = "ended", "fall", dt.datetime.now(dt.UTC)
            session.commit()
    finally:
        engine.dispose()


def test_a_live_run_is_timed_from_its_start_in_banners_and_charts(
    console: Any, clinic: dict[str, Any], console_service: dict[str, Any]
) -> None:
    """A run started 100 s ago on the worker's clock: the live charts run from 100 s (time into the run, not
    since the page opened nor the worker's uptime), and a fall event 25 s after the start reads "25.0 s into
    the run" in its banner."""
    import json

    headers = {"Authorization": f"Bearer {clinic['admin_token']}"}
    worker_now_s = httpx.get(f"{clinic['api']}/robot/state", headers=headers).json()["time_s"]
    run_start_s = worker_now_s - 100.0
    start = dt.datetime.fromisoformat(clinic["booking"]["start"]) + dt.timedelta(hours=3)
    booking = httpx.post(f"{clinic['api']}/sessions", headers=headers, json={
        "patient_id": clinic["patient"]["id"], "prescription_id": clinic["prescription"]["id"],
        "robot": "twin-banner", "start": start.isoformat(), "duration_s": 1800,
    }).json()[0]  # fmt: skip
    run_id = _seed_running_run(str(console_service["database_url"]), booking, start_tick_time_s=run_start_s)
    try:
        session = console()
        page = session.login()

        armed: list[bool] = []  # set once the page follows the run: the next frame brings the fall
        injected: list[bool] = []

        def relay(browser_socket: Any) -> None:  # the real telemetry, with one fall event added
            server = browser_socket.connect_to_server()

            def to_browser(message: str | bytes) -> None:
                frame = json.loads(message)
                if armed and frame.get("state") and not injected:
                    injected.append(True)
                    frame["events"] = [{"kind": "fall", "tick_time_s": run_start_s + 25.0, "detector": "harness_load",
                                        "details": {"harness_load_n": 412.0}}]  # fmt: skip
                browser_socket.send(json.dumps(frame))

            server.on_message(to_browser)

        page.route_web_socket(re.compile(r"/telemetry$"), relay)
        session.go(f"#/session/{booking['id']}")
        expect(page.locator("#stop-button")).to_be_enabled(timeout=20_000)  # the run is followed live
        expect(page.locator("#charts-title")).to_contain_text("time into the run")
        charted_s = float(page.locator("#live-charts").get_attribute("data-last-time") or "nan")
        assert 100.0 <= charted_s < 160.0, f"the live charts are at {charted_s} s, not about 100 s into the run"
        armed.append(True)
        fall = page.locator(".banner.fall").filter(has_text="FALL DETECTED")
        expect(fall).to_contain_text("25.0 s into the run", timeout=20_000)
    finally:
        _end_run(str(console_service["database_url"]), run_id)


# --- defect 9: broken and stale UI -------------------------------------------------------------------------------


def test_session_console_loads_without_script_errors(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    for _ in range(3):
        session.go("#/patients")
        expect(page.get_by_role("heading", name="Patients")).to_be_visible()
        session.go(f"#/session/{clinic['booking']['id']}")
        expect(page.get_by_role("heading", name="Session console")).to_be_visible()
        page.wait_for_timeout(2500)  # telemetry frames arrive while the page is still loading
    assert not session.errors, f"JavaScript errors in the session console: {session.errors}"


def test_runs_panel_keeps_choices_and_buttons(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    session.go(f"#/session/{clinic['fall_booking']['id']}")
    fmt = page.get_by_label(re.compile("Export format for run"))
    expect(fmt).to_be_visible()
    fmt.select_option("parquet")
    handle = page.locator(f'#runs [data-run-id="{clinic["fall_run_id"]}"]').element_handle()
    page.wait_for_timeout(7000)  # two refreshes of the runs (every 3 s)
    assert handle.evaluate("el => el.isConnected"), "the run's panel was rebuilt: buttons detach mid-click"
    expect(fmt).to_have_value("parquet")


def _new_prescription(console: Any, clinic: dict[str, Any], name: str) -> Any:
    session = console()
    page = session.login()
    session.go(f"#/prescriptions/new?patient={clinic['patient']['id']}")
    page.get_by_label("Prescription name").fill(name)
    page.get_by_label("Duration").fill("20")
    return page


def test_heading_follows_the_saved_version(console: Any, clinic: dict[str, Any]) -> None:
    page = _new_prescription(console, clinic, "Versioned sway")
    page.get_by_role("button", name="Save prescription").click()
    expect(page.get_by_role("heading", name="Prescription: Versioned sway (v1)")).to_be_visible()
    page.get_by_label("Duration").fill("25")
    page.get_by_role("button", name="Save as new version").click()
    expect(page.get_by_role("heading", name="Prescription: Versioned sway (v2)")).to_be_visible()


def test_error_banner_goes_after_success(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    session.go("#/patients/new")
    fill_patient(page, clinic["patient"]["identifier"], "Erika Beispiel", "1961-07-08", "female", "165", "60")  # taken
    page.get_by_role("button", name="Create patient").click()
    expect(page.locator(".banner.error, .field-error").first).to_be_visible()
    page.get_by_label("Record number").fill("MRN-DEF-2")
    page.get_by_role("button", name="Create patient").click()
    expect(page.get_by_role("heading", name="Erika Beispiel")).to_be_visible()
    expect(page.locator(".banner.error")).to_have_count(0)


def test_login_page_shows_no_navigation(console: Any) -> None:
    session = console()
    page = session.go("#/login")
    expect(page.get_by_role("button", name="Log in")).to_be_visible()
    expect(page.locator("#nav")).to_be_hidden()
    expect(page.get_by_role("button", name="Log out")).to_be_hidden()
    session.login()
    expect(page.locator("#nav")).to_be_visible()
    page.get_by_role("button", name="Log out").click()
    expect(page.get_by_role("button", name="Log in")).to_be_visible()
    expect(page.locator("#nav")).to_be_hidden()
    expect(page.get_by_role("button", name="Log out")).to_be_hidden()


PLACEHOLDERS_CUT_JS = """() => {
  const canvas = document.createElement('canvas').getContext('2d');
  return [...document.querySelectorAll('input[placeholder], textarea[placeholder]')]
    .filter((el) => el.getClientRects().length && el.placeholder).filter((el) => {
      const style = getComputedStyle(el);
      canvas.font = `${style.fontWeight} ${style.fontSize} ${style.fontFamily}`;
      const room = el.clientWidth - parseFloat(style.paddingLeft) - parseFloat(style.paddingRight);
      return canvas.measureText(el.placeholder).width > room;
    }).map((el) => `${el.placeholder} (${el.clientWidth} px)`);
}"""


def test_booking_form_fields_apart_and_dialog_closes(console: Any, clinic: dict[str, Any]) -> None:
    session = console(viewport=(1024, 768))
    page = session.login()
    start = dt.datetime.fromisoformat(clinic["booking"]["start"]).astimezone()
    session.go(f"#/schedule?week={start.date().isoformat()}")
    expect(page.get_by_role("heading", name="Book a session")).to_be_visible()
    overlaps = page.evaluate("""() => {
      const boxes = [...document.querySelectorAll('form .form-grid .field')].map((f) =>
        [...f.querySelectorAll('input, select')].map((el) => el.getBoundingClientRect())).flat();
      const hits = [];
      boxes.forEach((a, i) => boxes.forEach((b, j) => {
        const apart = a.right - 1 <= b.left || b.right - 1 <= a.left || a.bottom - 1 <= b.top || b.bottom - 1 <= a.top;
        if (i < j && !apart) hits.push([i, j]);
      }));
      return hits;
    }""")
    assert not overlaps, f"booking form controls overlap: {overlaps}"
    cut = page.evaluate(PLACEHOLDERS_CUT_JS)
    assert not cut, f"placeholders cut off: {cut}"
    booking = page.locator("button.booking").filter(has_text="Jürgen Äbischer").first
    booking.click()
    expect(page.locator("dialog[open]")).to_have_count(1)
    page.get_by_role("link", name="Open session console").click()
    expect(page.get_by_role("heading", name="Session console")).to_be_visible()
    expect(page.locator("dialog[open]")).to_have_count(0)
    # Any other way to the next page (the browser's Back, a link from a banner) closes the dialog too.
    page.go_back()
    booking.click()
    expect(page.locator("dialog[open]")).to_have_count(1)
    page.evaluate("location.hash = '#/history'")
    expect(page.get_by_role("heading", name="Session history")).to_be_visible()
    expect(page.locator("dialog[open]")).to_have_count(0)


def test_placeholders_whole(console: Any, clinic: dict[str, Any]) -> None:
    session = console(viewport=(1024, 768))
    page = session.login()
    routes = ["#/patients", f"#/prescriptions/new?patient={clinic['patient']['id']}",
              f"#/prescriptions/{clinic['prescription']['id']}", "#/schedule"]  # fmt: skip
    for route in routes:
        session.go(route)
        page.wait_for_selector("#main h1")
        page.wait_for_timeout(300)
        cut = page.evaluate(PLACEHOLDERS_CUT_JS)
        assert not cut, f"{route}: placeholders cut off: {cut}"


def test_refused_prescription_warns_before_saving(console: Any, clinic: dict[str, Any]) -> None:
    page = _new_prescription(console, clinic, "Too wide")
    page.get_by_label("Amplitude").fill("3")
    page.get_by_label("Frequency").fill("0.1")  # 3 m/s² at 0.1 Hz needs metres of travel
    page.get_by_role("button", name="Preview motion").click()
    expect(page.locator(".verdict")).to_contain_text("refuse", timeout=60_000)
    page.get_by_role("button", name="Save prescription").click()
    dialog = page.locator("dialog[open]")
    expect(dialog).to_be_visible()
    expect(dialog).to_contain_text("refuse")
    dialog.get_by_role("button", name="Cancel").click()  # the warning is a real choice: cancel saves nothing
    expect(page.locator("dialog[open]")).to_have_count(0)
    expect(page.get_by_role("heading", name="New prescription")).to_be_visible()
    saved = httpx.get(f"{clinic['api']}/prescriptions", params={"patient_id": clinic["patient"]["id"]},
                      headers={"Authorization": f"Bearer {clinic['admin_token']}"}).json()  # fmt: skip
    assert "Too wide" not in [p["name"] for p in saved], saved


# --- defect 8: the clinician's language ------------------------------------------------------------------------


def test_errors_in_screen_units_and_numbering(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    session.go("#/patients/new")
    fill_patient(page, "MRN-DEF-3", "Hans Gross", "1955-01-01", "male", "300", "80")
    page.get_by_role("button", name="Create patient").click()
    error = field_error(page, "Height")
    expect(error).to_contain_text("250 cm")
    expect(error).not_to_contain_text("0.5")
    session.go(f"#/prescriptions/new?patient={clinic['patient']['id']}")
    page.get_by_label("Prescription name").fill("Too strong")
    page.get_by_label("Amplitude").fill("50")
    page.get_by_role("button", name="Save prescription").click()
    message = page.locator(".field-error, .banner.error").first
    expect(message).to_be_visible()
    text = page.locator("#main").inner_text() + page.locator("#banners").inner_text()
    assert "segments[" not in text and "amplitude_m_s2" not in text, text
    expect(message).to_contain_text("m/s²")
    expect(page.locator(".segment").first.locator(".field-error")).to_contain_text("Segment 1")


def test_reset_refusal_in_plain_words(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    session.go(f"#/session/{clinic['booking']['id']}")
    expect(page.get_by_role("heading", name="Session console")).to_be_visible()
    page.get_by_role("button", name="Reset robot").click()
    shown = page.locator("#banners .banner").last
    expect(shown).to_be_visible()
    assert "TransitionRefused" not in shown.inner_text() and "not accepted in state" not in shown.inner_text()


def test_events_in_words_and_engineering_behind_a_switch(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    session.go(f"#/session/{clinic['fall_booking']['id']}")
    row = page.locator('#runs tr[data-kind="fall"]')
    expect(row).to_contain_text("Fall detected")
    expect(row).to_contain_text("harness load 412 N")
    expect(row).to_contain_text("25.0 s")  # time into the session
    expect(row.locator("details")).not_to_have_attribute("open", "")
    expect(page.get_by_text("Tick compute time")).to_be_hidden()
    turn_engineering_on(page)
    expect(page.get_by_text("Tick compute time")).to_be_visible()


# --- defect 10: API docs offline ------------------------------------------------------------------------------


def test_api_docs_render_offline(console: Any) -> None:
    session = console(offline=True)
    page = session.go("docs")
    expect(page.locator(".swagger-ui .info .title")).to_contain_text("ssp-rehab console", timeout=30_000)
    expect(page.locator(".opblock").first).to_be_visible()
    page = session.go("redoc")
    expect(page.locator("h1").first).to_contain_text("ssp-rehab console", timeout=30_000)
