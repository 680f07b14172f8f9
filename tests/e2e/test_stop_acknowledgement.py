"""Issue 20, defect 12 / build 9 in the browser: after an emergency stop and a reset, the red banners go
and the next step shows (acknowledge the stop, then start); Start stays disabled until the acknowledgement;
at 1024×768 "Reset robot" is visible without scrolling while the header and two red banners show."""

from __future__ import annotations

import datetime as dt
import json
import re
import time
from typing import Any

import httpx
import pytest

from tests.e2e.conftest import ARTIFACTS, acknowledge_earlier_stop

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

expect = pytest.importorskip("playwright.sync_api").expect

VIEWPORT = (1024, 768)


def _click(locator: Any) -> None:
    """A DOM click: with the 3D view rendering in software on a loaded machine, Playwright's pointer actions
    wait for animation frames that come too seldom (tests/e2e/conftest.py, turn_engineering_on)."""
    locator.evaluate("element => element.click()")


def _book(clinic: dict[str, Any], hours_after_the_clinic_booking: int) -> dict[str, Any]:
    """A booking of the clinic's prescription on twin-1, on a robot with no earlier stop to acknowledge."""
    acknowledge_earlier_stop(clinic)  # a stop another browser test left on this robot
    headers = {"Authorization": f"Bearer {clinic['admin_token']}"}
    start = dt.datetime.fromisoformat(clinic["booking"]["start"]) + dt.timedelta(hours=hours_after_the_clinic_booking)
    with httpx.Client(base_url=clinic["api"], headers=headers, timeout=60) as api:
        return dict(api.post("/sessions", json={
            "patient_id": clinic["patient"]["id"], "prescription_id": clinic["prescription"]["id"],
            "robot": "twin-1", "start": start.isoformat(), "duration_s": 1800,
        }).json()[0])  # fmt: skip


def _confirm_checklist(page: Any) -> None:
    dialog = page.locator("#confirm-dialog")
    expect(dialog).to_be_visible()
    for box in dialog.get_by_role("checkbox").all():
        _click(box)
        expect(box).to_be_checked()
    expect(page.locator("#confirm-ok")).to_be_enabled()
    _click(page.locator("#confirm-ok"))


def _running_session(console: Any, clinic: dict[str, Any], hours_after_the_clinic_booking: int) -> tuple[Any, Any]:
    """A browser session whose booking's run is moving: (session, page)."""
    booking = _book(clinic, hours_after_the_clinic_booking)
    session = console(viewport=VIEWPORT)
    # Without the 3D view: its software WebGL starves this page's main thread on a loaded machine, and it is
    # not what these tests are about (the page keeps its place: "3D view unavailable").
    session.context.route(re.compile(r"/api/v1/viz/view/"), lambda route: route.abort())
    session.page.set_default_timeout(60_000)
    page = session.login()
    session.go(f"#/session/{booking['id']}")
    start_button = page.locator("#start-button")
    expect(start_button).to_be_enabled(timeout=30_000)
    _click(start_button)
    _confirm_checklist(page)
    expect(page.locator("#run-state")).to_have_attribute("data-state", "running", timeout=120_000)
    return session, page


def test_after_an_estop_and_a_reset_the_stop_is_acknowledged_before_the_next_start(
    console: Any, clinic: dict[str, Any]
) -> None:
    session, page = _running_session(console, clinic, hours_after_the_clinic_booking=5)
    start_button, reset_button = page.locator("#start-button"), page.locator("#reset-button")

    _click(page.locator("#estop"))
    estop_banner = page.locator('.banner.error[data-key="estop"]')
    robot_banner = page.locator('.banner.error[data-key="robot-alert"]')
    expect(estop_banner).to_be_visible(timeout=60_000)  # the stop's answer, on a page a loaded machine starves
    expect(robot_banner).to_be_visible(timeout=60_000)
    expect(page.locator("#run-state")).to_have_attribute("data-state", "emergency_stop", timeout=30_000)

    # The header and two red banners shown: "Reset robot" is still on screen without scrolling.
    page.evaluate("() => window.scrollTo(0, 0)")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(ARTIFACTS / "estop-two-banners-1024x768.png"))
    box = reset_button.bounding_box()
    assert box is not None and box["y"] >= 0 and box["y"] + box["height"] <= VIEWPORT[1], (
        f"'Reset robot' is at y = {box and box['y']:.0f}..{box and box['y'] + box['height']:.0f} px: below the "
        f"{VIEWPORT[1]} px window, under the header and the banners"
    )
    expect(start_button).to_be_disabled()

    _click(reset_button)
    expect(page.locator("#robot-status")).to_contain_text("READY", timeout=30_000)
    # The red banners clear once the robot is reset; the next step says what to do, in order.
    expect(estop_banner).to_have_count(0, timeout=15_000)
    expect(robot_banner).to_have_count(0)
    next_step = page.locator('.banner[data-key="robot-next"]')
    expect(next_step).to_contain_text("acknowledge the emergency stop", timeout=15_000)
    expect(next_step).to_contain_text("then start")
    page.screenshot(path=str(ARTIFACTS / "after-reset-next-step-1024x768.png"))
    # The robot is ready, but Start waits for the acknowledgement.
    expect(start_button).to_be_disabled()
    acknowledge = page.locator("#acknowledge-button")
    expect(acknowledge).to_be_in_viewport()
    _click(acknowledge)
    _confirm_checklist(page)
    expect(next_step).to_have_count(0, timeout=15_000)
    expect(start_button).to_be_enabled(timeout=15_000)
    assert not session.errors, session.errors


def test_start_is_enabled_only_once_a_click_opens_the_checklist(console: Any, clinic: dict[str, Any]) -> None:
    """CI failure, 2026-12-07: the page built an enabled Start, then waited for the 3D view's status before it
    wired the button; telemetry said READY meanwhile, and a click did nothing. The 3D view's status is held here
    until Start has been looked at."""
    booking = _book(clinic, hours_after_the_clinic_booking=6)
    session = console(viewport=VIEWPORT)
    session.context.route(re.compile(r"/api/v1/viz/view/"), lambda route: route.abort())
    held: list[Any] = []
    viz_status = re.compile(r"/api/v1/viz$")
    session.context.route(viz_status, lambda route: held.append(route))
    session.page.set_default_timeout(60_000)
    page = session.login()
    session.go(f"#/session/{booking['id']}")
    start_button = page.locator("#start-button")
    # The page is built and the robot is READY (telemetry arrives), while the 3D view's status is still held.
    expect(page.locator("#robot-status")).to_contain_text("READY", timeout=30_000)
    expect(page.locator("#plan-state")).to_contain_text("ready", timeout=60_000)
    expect(start_button).to_be_disabled()
    assert held, "the 3D view's status was not asked for"
    session.context.unroute(viz_status)
    for route in held:
        route.continue_()
    expect(start_button).to_be_enabled(timeout=30_000)
    _click(start_button)
    dialog = page.locator("#confirm-dialog")
    expect(dialog).to_be_visible()
    _click(dialog.get_by_role("button", name="Cancel"))
    expect(dialog).to_be_hidden()
    expect(page.locator("#run-state")).not_to_have_attribute("data-state", "running")
    assert not session.errors, session.errors


def test_a_robot_state_asked_before_the_stop_and_answered_after_it_does_not_undo_it(
    console: Any, clinic: dict[str, Any]
) -> None:
    """A full test run's failure, 2026-12-08: the page polls /robot/state every 2 s beside the live telemetry. A
    poll asked while the run moved and answered after the telemetry had shown the emergency stop took the top bar
    back to MOVING and cleared the stop's banner for good, while the robot was latched."""
    session, page = _running_session(console, clinic, hours_after_the_clinic_booking=7)
    headers = {"Authorization": f"Bearer {clinic['admin_token']}"}
    moving = httpx.get(f"{clinic['api']}/robot/state", headers=headers, timeout=60).json()
    assert moving["state"] == "running", moving

    # The next poll is held, then answered with what the robot said while it moved: a slow answer.
    held: list[Any] = []
    robot_state = re.compile(r"/api/v1/robot/state$")
    session.context.route(robot_state, lambda route: held.append(route) if not held else route.continue_())
    deadline = time.monotonic() + 60.0
    while not held:
        assert time.monotonic() < deadline, "the page did not poll the robot's state within 60 s"
        page.wait_for_timeout(100)
    _click(page.locator("#estop"))
    estop_banner = page.locator('.banner.error[data-key="estop"]')
    expect(estop_banner).to_be_visible(timeout=60_000)
    expect(page.locator("#robot-status")).to_contain_text("E-STOP LATCHED", timeout=60_000)
    with page.expect_response(robot_state):
        held[0].fulfill(status=200, content_type="application/json", body=json.dumps(moving))
    # The page handles that answer before the poll after it (one thread; the next poll comes 2 s later).
    with page.expect_request(robot_state, timeout=60_000):
        pass
    expect(estop_banner).to_have_count(1)
    expect(page.locator("#robot-status")).to_contain_text("E-STOP LATCHED")
    session.context.unroute(robot_state)
    assert not session.errors, session.errors
