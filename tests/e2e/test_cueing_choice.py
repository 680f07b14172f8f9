"""Issue 14 §5 in a real browser: the prescription editor offers the choice of motion cueing, sends it with
the preview and on save, shows it on the prescription's page, and the preview shows the perceived motion at
the patient's head for the algorithm chosen."""

from __future__ import annotations

import re
from typing import Any

import httpx
import pytest

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

playwright_api = pytest.importorskip("playwright.sync_api")
expect = playwright_api.expect

CLASSICAL = "Classical washout (paper)"
OPTIMAL = "Optimal (planned over the whole prescription)"


def test_the_editor_offers_optimal_cueing_previews_it_and_stores_it(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    session.go(f"#/prescriptions/new?patient={clinic['patient']['id']}")
    page.get_by_label("Prescription name").fill("Sway planned")
    page.get_by_label("Duration", exact=True).fill("15")
    choice = page.get_by_label("Motion cueing")
    expect(choice).to_have_value("classical")  # the paper's method stays the default
    expect(choice.locator("option")).to_have_text([CLASSICAL, OPTIMAL])

    # A preview with the default, then the choice changed: the preview is computed again for optimal.
    with page.expect_request("**/api/v1/prescriptions/previews") as first:
        page.get_by_role("button", name="Preview motion").click()
    assert first.value.post_data_json["cueing"] == "classical"
    expect(page.locator(".verdict")).to_contain_text("accepts", timeout=90_000)
    expect(page.locator("#preview-cueing")).to_contain_text(CLASSICAL)
    with page.expect_request("**/api/v1/prescriptions/previews") as second:
        choice.select_option("optimal")
    assert second.value.post_data_json["cueing"] == "optimal"
    # A job of the planner (issue 21, defect 6): the status line shows how far it is while it plans.
    status = page.locator('p.panel[role="status"]')
    expect(status).to_contain_text(re.compile(r"Computing the preview \(Optimal.*\d+ %"))
    expect(status.locator("progress")).to_have_count(1)
    expect(page.locator("#preview-cueing")).to_contain_text(OPTIMAL, timeout=90_000)
    expect(page.locator(".verdict")).to_contain_text("accepts")
    perceived = f'.charts .chart[aria-label^="Perceived acceleration at the head"][aria-label*="{OPTIMAL}"]'
    expect(page.locator(perceived)).to_have_count(1)
    expect(page.locator('.charts .chart[aria-label^="Tilt rate the cue does not ask for"]')).to_have_count(1)

    # Saved with the choice: the API stores it, the prescription's page shows it and reads it back.
    with page.expect_request(lambda r: r.url.endswith("/api/v1/prescriptions") and r.method == "POST") as saved:
        page.get_by_role("button", name="Save prescription").click()
    assert saved.value.post_data_json["cueing"] == "optimal"
    expect(page.get_by_role("heading", name="Prescription: Sway planned (v1)")).to_be_visible(timeout=90_000)
    headers = {"Authorization": f"Bearer {clinic['admin_token']}"}
    stored = httpx.get(
        f"{clinic['api']}/prescriptions", params={"patient_id": clinic["patient"]["id"]}, headers=headers, timeout=30
    ).json()
    (record,) = [p for p in stored if p["name"] == "Sway planned"]
    assert record["current"]["content"]["cueing"] == "optimal"
    expect(page.get_by_label("Motion cueing")).to_have_value("optimal")
    expect(page.locator("#prescription-cueing")).to_contain_text(f"Motion cueing: {OPTIMAL}")
    assert not session.errors, session.errors
