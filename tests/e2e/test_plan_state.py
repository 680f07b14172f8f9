"""Issue 21 §1: the booking shows its motion plan's state in words. Opening a booking on the schedule asks
the robot for its plan (queued if it is not built yet) and follows it until it is ready."""

from __future__ import annotations

import datetime as dt
from typing import Any

import pytest

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

playwright_api = pytest.importorskip("playwright.sync_api")
expect = playwright_api.expect

PLAN_READY_TIMEOUT_MS = 300_000  # planning and checking a booking on a loaded machine


def test_the_booking_dialog_follows_its_plan_until_it_is_ready(console: Any, clinic: dict[str, Any]) -> None:
    session = console(viewport=(1280, 800))
    page = session.login()
    start = dt.datetime.fromisoformat(clinic["booking"]["start"]).astimezone()
    session.go(f"#/schedule?week={start.date().isoformat()}")
    page.locator("button.booking").filter(has_text="Jürgen Äbischer").first.click()
    plan = page.locator("dialog[open] #booking-plan-state")
    expect(plan).to_have_attribute("data-state", "ready", timeout=PLAN_READY_TIMEOUT_MS)
    expect(plan).to_have_text("ready: checked sample by sample; Start plays it at once")
