"""Cross-site request forgery in a real browser (issue 12 defect 7): a page on another port of the same host
auto-submits a form POST to `/sessions/N/start` while the clinician is logged in. The session cookie is
SameSite=Strict, but another port is the same *site*, so the browser sends it; only the console's Origin and
header check stands in the way. The console's own pages (under its CSP) keep working, the 3D view included."""

from __future__ import annotations

import contextlib
import http.server
import threading
from collections.abc import Iterator
from typing import Any

import httpx
import pytest

from tests.e2e.conftest import ADMIN, free_port
from tests.server.conftest import PATIENT, SEGMENT

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

playwright_api = pytest.importorskip("playwright.sync_api")
expect = playwright_api.expect


def _booked_session(api: httpx.Client) -> int:
    patient = api.post("/api/v1/patients", json={**PATIENT, "identifier": "MRN-CSRF-1"})
    assert patient.status_code == 201, patient.text
    patient_id = patient.json()["id"]
    prescription = api.post(
        "/api/v1/prescriptions",
        json={"patient_id": patient_id, "name": "CSRF probe", "segments": [{**SEGMENT, "duration_s": 20.0}]},
    )
    assert prescription.status_code == 201, prescription.text
    booking = api.post(
        "/api/v1/sessions",
        json={
            "patient_id": patient_id,
            "prescription_id": prescription.json()["id"],
            "robot": "twin-1",
            "start": "2031-05-06T09:00:00+00:00",
            "duration_s": 1800,
        },
    )
    assert booking.status_code == 201, booking.text
    return int(booking.json()[0]["id"])


@contextlib.contextmanager
def attacker_site(target: str) -> Iterator[str]:
    """Another port on the same host, serving a page that auto-submits a form POST to `target`."""
    page = (
        f'<!doctype html><form id="f" method="POST" action="{target}"><input name="x" value="1"></form>'
        '<script>document.getElementById("f").submit()</script>'
    ).encode()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(page)))
            self.end_headers()
            self.wfile.write(page)

        def log_message(self, *_args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", free_port()), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}/"
    finally:
        server.shutdown()
        server.server_close()


def test_a_form_posted_from_another_port_does_not_start_a_session(
    console_service: dict[str, object], browser: Any
) -> None:
    base_url = str(console_service["base_url"])
    with httpx.Client(base_url=base_url, timeout=60) as anonymous:
        login = anonymous.post("/api/v1/auth/login", json={"username": ADMIN[0], "password": ADMIN[1]})
    assert login.status_code == 200, login.text
    token = login.json()["access_token"]
    with httpx.Client(base_url=base_url, timeout=120, headers={"Authorization": f"Bearer {token}"}) as api:
        session_id = _booked_session(api)
        start_url = f"{base_url}/api/v1/sessions/{session_id}/start"
        with attacker_site(start_url) as attacker_url:
            context = browser.new_context()  # the suite's one browser (one Playwright per thread)
            context.add_cookies(
                [{"name": "ssp_rehab_session", "value": token, "url": base_url, "httpOnly": True, "sameSite": "Strict"}]
            )
            page = context.new_page()
            page.set_default_timeout(60_000)
            try:
                with page.expect_response(lambda response: response.url == start_url) as forged:
                    page.goto(attacker_url)
                assert forged.value.request.method == "POST"
                assert "ssp_rehab_session" in (forged.value.request.header_value("cookie") or "")  # it was sent
                assert forged.value.status == 403, forged.value.text()
                assert api.get(f"/api/v1/sessions/{session_id}/runs").json() == []

                # The console's own page, under its CSP: it logs in with the cookie, its calls pass the check,
                # and no policy violation is reported.
                violations: list[str] = []
                page.on(
                    "console",
                    lambda message: (
                        violations.append(message.text) if "Content Security Policy" in message.text else None
                    ),
                )
                page.goto(f"{base_url}/#/session/{session_id}")
                expect(page.locator("#viz-frame")).to_be_visible()
                expect(page.frame_locator("#viz-frame").locator("canvas").first).to_be_visible(timeout=120_000)
                # The console's own request passes the check: it reaches the route, which refuses only
                # because nothing runs (409, not 403). Pausing moves nothing, so later tests find the robot idle.
                own = page.evaluate(
                    """async (url) => {
                        const response = await fetch(url, {method: "POST", credentials: "same-origin",
                                                           headers: {"X-Requested-With": "ssp-rehab"}});
                        return [response.status, await response.text()];
                    }""",
                    start_url.replace("/start", "/pause"),
                )
                assert own[0] == 409 and "no active run" in own[1], own
                assert violations == []
            finally:
                context.close()
                if api.get(f"/api/v1/sessions/{session_id}/runs").json():  # the forgery got through
                    api.post(f"/api/v1/sessions/{session_id}/stop")
