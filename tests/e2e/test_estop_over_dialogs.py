"""Issue 20, defect 1: the emergency stop over every dialog. With a dialog open, the red button must be
visible, undimmed, on top where it is drawn, reachable by Tab, and a real mouse click on it must send the stop
and get its answer; Escape must stop as well."""

from __future__ import annotations

import datetime as dt
import time
from collections.abc import Callable
from typing import Any

import pytest

from tests.e2e.conftest import acknowledge_earlier_stop, reset_latched_stop

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

playwright_api = pytest.importorskip("playwright.sync_api")
expect = playwright_api.expect

STOP_ANSWER_TIMEOUT_MS = 90_000  # the stop answers within a second; a starved renderer (software WebGL) is slow to act
TAB_PRESSES = 30

ESTOP_REACHABLE_JS = """() => {
  const button = document.getElementById('estop');
  const box = button.getBoundingClientRect();
  const hit = document.elementFromPoint(box.left + box.width / 2, box.top + box.height / 2);
  let opacity = 1;
  for (let el = button; el; el = el.parentElement) opacity *= Number(getComputedStyle(el).opacity);
  return { covered: !(hit && button.contains(hit)), hit: hit ? hit.outerHTML.slice(0, 80) : null, opacity,
           inert: button.closest('[inert]') !== null, visible: box.width > 0 && box.height > 0 };
}"""


def _open_booking(page: Any, clinic: dict[str, Any], go: Callable[[str], Any]) -> None:
    start = dt.datetime.fromisoformat(clinic["booking"]["start"]).astimezone()
    go(f"#/schedule?week={start.date().isoformat()}")
    page.locator("button.booking").filter(has_text="Jürgen Äbischer").first.click()


def _open_start(page: Any, clinic: dict[str, Any], go: Callable[[str], Any]) -> None:
    acknowledge_earlier_stop(clinic)
    go(f"#/session/{clinic['booking']['id']}")
    # The console wires its buttons once the page's data has loaded: click until the dialog answers.
    deadline = time.monotonic() + 60.0
    while page.locator("dialog[open]").count() == 0:
        assert time.monotonic() < deadline, "the Start button never opened its dialog"
        expect(page.locator("#start-button")).to_be_enabled(timeout=60_000)
        page.locator("#start-button").click()
        page.wait_for_timeout(500)


def _open_password(page: Any, clinic: dict[str, Any], go: Callable[[str], Any]) -> None:
    go("#/admin")
    page.get_by_role("button", name="Set a new password").first.click()


def _open_account_change(page: Any, clinic: dict[str, Any], go: Callable[[str], Any]) -> None:
    go("#/admin")
    page.locator("tr[data-user] button").filter(has_text="Deactivate").first.click()


DIALOGS = {
    "booking": _open_booking,
    "start": _open_start,
    "new-password": _open_password,
    "account-change": _open_account_change,
}


def _is_stop_request(response: Any) -> bool:
    return response.request.method == "POST" and response.url.split("?")[0].endswith("/estop")


@pytest.mark.parametrize("dialog", list(DIALOGS))
def test_estop_over_every_dialog(console: Any, clinic: dict[str, Any], dialog: str) -> None:
    session = console(viewport=(1280, 800))
    page = session.login()
    try:
        DIALOGS[dialog](page, clinic, session.go)
        expect(page.locator("dialog[open]")).to_have_count(1)

        reach = page.evaluate(ESTOP_REACHABLE_JS)
        assert reach["visible"], f"{dialog}: the emergency stop is not drawn ({reach})"
        assert not reach["covered"], f"{dialog}: the dialog covers the emergency stop: a click lands on {reach['hit']}"
        assert reach["opacity"] == 1, f"{dialog}: the emergency stop is dimmed (opacity {reach['opacity']})"
        assert not reach["inert"], f"{dialog}: the emergency stop is inert behind the dialog"

        focused = []
        for _ in range(TAB_PRESSES):
            page.keyboard.press("Tab")
            focused.append(page.evaluate("() => document.activeElement && document.activeElement.id"))
            if focused[-1] == "estop":
                break
        assert "estop" in focused, f"{dialog}: Tab never reaches the emergency stop (focus went to {focused})"

        box = page.locator("#estop").bounding_box()
        with page.expect_response(_is_stop_request, timeout=STOP_ANSWER_TIMEOUT_MS) as stop:
            page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        assert stop.value.status == 200, f"{dialog}: the stop answered {stop.value.status}: {stop.value.text()}"
        expect(page.locator('.banner.error[data-key="estop"]')).to_be_visible()
        reset_latched_stop(clinic)

        # Escape stops too, with the dialog still open (a click on the button may have left it open).
        if page.locator("dialog[open]").count() == 0:
            DIALOGS[dialog](page, clinic, session.go)
            expect(page.locator("dialog[open]")).to_have_count(1)
        with page.expect_response(_is_stop_request, timeout=STOP_ANSWER_TIMEOUT_MS) as stop:
            page.keyboard.press("Escape")
        assert stop.value.status == 200, f"{dialog}: Escape's stop answered {stop.value.status}"
    finally:
        reset_latched_stop(clinic)
