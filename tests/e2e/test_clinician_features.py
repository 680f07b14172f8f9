"""Issue 16's new console pieces in a real browser: patient records (notes, edit, archive, no default sex,
accent-free search), administration, the protocol library, a form for every cue kind, the 3D view without
viser's developer panel and with labels and camera presets, and the PDF report from the history page."""

from __future__ import annotations

import datetime as dt
import io
import re
import time
from typing import Any

import pytest

from benchmarks.fault_harness import wait_for
from tests.e2e.conftest import ARTIFACTS, THERAPIST, field_error, fill_patient, turn_engineering_on
from tests.server.test_viz_proxy import preset_at, viser_messages

pytestmark = [pytest.mark.e2e, pytest.mark.slow]

playwright_api = pytest.importorskip("playwright.sync_api")
expect = playwright_api.expect

PROTOCOL_NAMES = [
    "Progressive lateral sway",
    "Perturbation levels",
    "Gait-like work",
    "Sensory-organisation-style sequence",
]
RECORDED_CUE = "time_s,specific_force_x_m_s2,specific_force_y_m_s2,specific_force_z_m_s2\n" + "".join(
    f"{t / 10:.1f},0,{0.3 if (t // 20) % 2 else -0.3},0\n" for t in range(0, 201)
)


def test_patient_notes_edit_archive_and_no_default_sex(console: Any) -> None:
    session = console()
    page = session.login()
    session.go("#/patients/new")
    expect(page.get_by_label("Sex")).to_have_value("")  # no silent default
    fill_patient(page, "MRN-FEAT-1", "Ørjan Lindqvist", "1948-11-12", None, "171", "70")
    page.get_by_label("Notes").fill("hearing aid on the left")
    page.get_by_role("button", name="Create patient").click()
    expect(field_error(page, "Sex")).to_contain_text("Sex")
    page.get_by_label("Sex").select_option("male")
    page.get_by_role("button", name="Create patient").click()
    expect(page.get_by_role("heading", name="Ørjan Lindqvist")).to_be_visible()
    expect(page.locator("#patient-notes")).to_contain_text("hearing aid on the left")

    page.get_by_role("link", name="Edit patient").click()
    expect(page.get_by_label("Height")).to_have_value("171")
    page.get_by_label("Body mass").fill("72.5")
    page.get_by_role("button", name="Save patient").click()
    expect(page.get_by_role("heading", name="Ørjan Lindqvist")).to_be_visible()
    expect(page.locator(".metric").filter(has_text="Body mass")).to_contain_text("72.5 kg")

    page.get_by_role("button", name="Archive patient").click()
    page.locator("#confirm-ok").click()
    expect(page.get_by_text("Archived on")).to_be_visible()
    session.go("#/patients")
    search = page.get_by_label("Search patients")
    search.fill("orjan")  # accents ignored
    expect(page.get_by_text("No patient matches.")).to_be_visible()
    page.get_by_label("Show archived records").check()
    expect(page.locator("tr").filter(has_text="Ørjan Lindqvist")).to_be_visible()
    assert not session.errors, session.errors


def test_search_ignores_accents(console: Any) -> None:
    session = console()
    page = session.login()
    page.get_by_label("Search patients").fill("jurgen abi")
    expect(page.locator("tbody tr")).to_have_count(1)
    expect(page.locator("tbody tr")).to_contain_text("Jürgen Äbischer")


def test_admin_manages_accounts_and_reads_the_audit_log(console: Any) -> None:
    session = console()
    page = session.login()
    page.get_by_role("link", name="Admin").click()
    expect(page.get_by_role("heading", name="Accounts")).to_be_visible()
    page.get_by_label("User name").fill("e2e-physio")
    page.get_by_label("Full name").fill("Pat Physio")
    page.get_by_label("Initial password").fill("physio-password-1")
    page.get_by_role("button", name="Create account").click()
    row = page.locator('tr[data-user="e2e-physio"]')
    expect(row).to_contain_text("Pat Physio")
    row.get_by_role("button", name="Deactivate").click()
    page.locator("#confirm-ok").click()
    expect(row).to_contain_text("deactivated")
    expect(page.locator("#audit tbody tr").first).to_be_visible()
    page.get_by_label("Kind of record").select_option("user")
    expect(page.locator("#audit tbody tr").filter(has_text="create")).not_to_have_count(0)

    therapist = console(user=THERAPIST)
    therapist.login()
    expect(therapist.page.get_by_role("link", name="Admin")).to_be_hidden()


def test_protocols_copy_to_a_patient_and_save_as_a_prescription(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    page.get_by_role("link", name="Protocols").click()
    for name in PROTOCOL_NAMES:
        expect(page.get_by_role("heading", name=name)).to_be_visible()
    sway = page.locator('section[data-protocol="progressive-lateral-sway"]')
    sway.get_by_label("Patient").select_option(str(clinic["patient"]["id"]))
    sway.get_by_role("button", name=re.compile("Copy")).click()
    expect(page.get_by_role("heading", name="New prescription")).to_be_visible()
    expect(page.locator(".segment")).to_have_count(4)
    expect(page.get_by_label("Prescription name")).to_have_value("Progressive lateral sway")
    page.locator(".segment").last.get_by_label("Duration").fill("45")  # adapted to the patient
    page.get_by_role("button", name="Save prescription").click()
    expect(page.get_by_role("heading", name="Prescription: Progressive lateral sway (v1)")).to_be_visible(
        timeout=60_000
    )
    # Every programme of the library passes the robot's own check as it stands.
    for key in ("perturbation-levels", "gait-like", "sensory-organisation-sequence"):
        session.go(f"#/prescriptions/new?patient={clinic['patient']['id']}&protocol={key}")
        page.get_by_role("button", name="Preview motion").click()
        expect(page.locator(".verdict")).to_contain_text("accepts", timeout=90_000)
    assert not session.errors, session.errors


@pytest.mark.parametrize("kind", ["step", "multisine", "csv_replay"])
def test_every_cue_kind_has_a_form(console: Any, clinic: dict[str, Any], kind: str) -> None:
    session = console()
    page = session.login()
    session.go(f"#/prescriptions/new?patient={clinic['patient']['id']}")
    page.get_by_label("Prescription name").fill(f"Cue form {kind}")
    page.get_by_label("Cue", exact=True).select_option(kind)
    page.get_by_label("Duration", exact=True).fill("20")
    if kind == "step":
        page.get_by_label("Level after the step").fill("0.4")
        page.get_by_label("Step at").fill("3")
    elif kind == "multisine":
        expect(page.get_by_label("Component 2: frequency")).to_be_visible()
        page.get_by_role("button", name="Add a component").click()
        page.get_by_label("Component 3: amplitude").fill("0.1")
        page.get_by_label("Component 3: frequency").fill("0.7")
    else:
        page.get_by_label("Recorded cue (CSV file)").set_input_files(
            files=[{"name": "sway.csv", "mimeType": "text/csv", "buffer": RECORDED_CUE.encode()}]
        )
        expect(page.get_by_text("201 rows loaded")).to_be_visible()
    page.get_by_role("button", name="Preview motion").click()
    expect(page.locator(".verdict")).to_contain_text("accepts", timeout=60_000)
    page.get_by_role("button", name="Save prescription").click()
    expect(page.get_by_role("heading", name=f"Prescription: Cue form {kind} (v1)")).to_be_visible(timeout=60_000)
    expect(page.get_by_label("Cue", exact=True)).to_have_value(kind)  # read back into the same form


def test_3d_view_shows_presets_without_viser_developer_panel_or_notice(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    session.go(f"#/session/{clinic['booking']['id']}")
    frame = page.frame_locator("#viz-frame")
    expect(frame.locator("canvas").first).to_be_visible(timeout=60_000)
    expect(frame.get_by_text("ssp-rehab 3D view")).to_be_visible(timeout=30_000)  # viser's panel, minimized
    expect(frame.get_by_role("button", name="Front")).to_be_hidden(timeout=20_000)
    turn_engineering_on(page)
    expect(frame.get_by_role("button", name="Front")).to_be_visible(timeout=20_000)  # the panel shows presets
    expect(frame.get_by_text("Dev Settings")).to_be_hidden(timeout=20_000)  # after viser's collapse animation
    # The FRONT / LEFT / RIGHT labels are drawn in the WebGL canvas (not DOM text): see test_viz_scene.py.
    page.wait_for_timeout(6000)  # viser shows its notice at load; the view takes it away
    expect(frame.get_by_text("Software WebGL rendering detected")).to_have_count(0)
    page.locator(".camera-presets").get_by_role("button", name="Left side").click()
    status = _viz_status(clinic, page)
    assert status["camera_preset"] == "left" and status["controls_visible"] is True, status
    assert status["figure_height_m"] == pytest.approx(clinic["patient"]["height_m"]), status


def _viz_status(clinic: dict[str, Any], page: Any) -> dict[str, Any]:
    """`GET /viz` as this browser sees it (its cookie: `controls_visible` is its own switch), once the view
    has taken the left preset."""
    seen: list[dict[str, Any]] = []

    def left() -> bool:
        seen.append(page.request.get(f"{clinic['api']}/viz").json())
        return seen[-1].get("camera_preset") == "left"

    try:
        wait_for(left, 60.0, "the left camera preset", 0.25)
    except AssertionError as error:
        raise AssertionError(f"{error}: {seen[-1]}") from None
    return seen[-1]


def test_the_engineering_switch_of_one_browser_leaves_the_other_browsers_3d_view(
    console: Any, clinic: dict[str, Any]
) -> None:
    """The therapist's tablet turns engineering on: viser's panel opens there, not on the wall screen (the
    same account, logged in on another device), not even after the wall screen reloads."""
    tablet, wall = console(user=THERAPIST[:2]), console(user=THERAPIST[:2])
    frames = {}
    for name, browser in (("tablet", tablet), ("wall", wall)):
        browser.login()
        browser.go(f"#/session/{clinic['booking']['id']}")
        frames[name] = browser.page.frame_locator("#viz-frame")
        expect(frames[name].get_by_text("ssp-rehab 3D view")).to_be_visible(timeout=60_000)  # viser's panel bar
        expect(frames[name].get_by_role("button", name="Front")).to_be_hidden(timeout=20_000)
    turn_engineering_on(tablet.page)
    expect(frames["tablet"].get_by_role("button", name="Front")).to_be_visible(timeout=20_000)
    wall.page.wait_for_timeout(3000)  # the time the tablet's panel took to open, and more
    expect(frames["wall"].get_by_role("button", name="Front")).to_be_hidden()
    wall.page.reload()
    expect(wall.page.frame_locator("#viz-frame").get_by_text("ssp-rehab 3D view")).to_be_visible(timeout=60_000)
    wall.page.wait_for_timeout(3000)
    expect(wall.page.frame_locator("#viz-frame").get_by_role("button", name="Front")).to_be_hidden()
    expect(wall.page.get_by_label("Engineering details")).not_to_be_checked()
    assert not tablet.errors and not wall.errors, (tablet.errors, wall.errors)


class CameraWatch:
    """A browser's 3D view: where viser's page says it looks from (each camera change sends a
    `ViewerCameraMessage` up the view's WebSocket; msgpack, position in m, world frame), and every camera move
    the console sent it (down the same socket, read as the network delivers it, however seldom the page
    paints with software WebGL)."""

    def __init__(self, page: Any) -> None:
        self.page = page
        self.position: tuple[float, ...] | None = None
        self.moves: list[str | None] = []  # the preset of each move sent to this browser
        page.on("websocket", self._watch)

    def _watch(self, socket: Any) -> None:
        if "/api/v1/viz/view" in socket.url:
            socket.on("framesent", self._sent)
            socket.on("framereceived", self._received)

    def _sent(self, payload: Any) -> None:
        import msgspec

        if isinstance(payload, bytes):
            message = msgspec.msgpack.decode(payload)
            if isinstance(message, dict) and message.get("type") == "ViewerCameraMessage":
                self.position = tuple(message["position"])

    def _received(self, payload: Any) -> None:
        if isinstance(payload, bytes):
            self.moves += [preset_at(tuple(m["position"]), 1e-6) for m in viser_messages(payload)
                           if m["type"] == "SetCameraPositionMessage" and not m["initial"]]  # fmt: skip

    def looks_from(self) -> str | None:
        return preset_at(self.position, 0.02)  # m: the page reports its camera in float32

    def wait_for(self, preset: str, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while self.looks_from() != preset and time.monotonic() < deadline:
            self.page.wait_for_timeout(200)  # Playwright delivers the socket's frames while it waits
        assert self.looks_from() == preset, f"the view looks from {self.position}, not from the {preset} preset"


def test_a_camera_preset_moves_the_3d_view_of_that_browser_only(console: Any, clinic: dict[str, Any]) -> None:
    """The therapist's tablet looks from the front: the wall screen (the same account, logged in on another
    device) keeps its overview, also after it reloads; the tablet's own reload looks from the front again."""
    tablet, wall = console(user=THERAPIST[:2]), console(user=THERAPIST[:2])
    cameras = {"tablet": CameraWatch(tablet.page), "wall": CameraWatch(wall.page)}
    for name, browser in (("tablet", tablet), ("wall", wall)):
        browser.login()
        browser.go(f"#/session/{clinic['booking']['id']}")
        expect(browser.page.frame_locator("#viz-frame").locator("canvas").first).to_be_visible(timeout=60_000)
        cameras[name].wait_for("oblique", timeout_s=60.0)
    tablet.page.locator(".camera-presets").get_by_role("button", name="Front").click()
    cameras["tablet"].wait_for("front")
    wall.page.wait_for_timeout(3000)  # the time the tablet's view took to turn, and more
    assert (cameras["wall"].moves, cameras["wall"].looks_from()) == ([], "oblique"), cameras["wall"].position
    for name, browser, preset in (("wall", wall, "oblique"), ("tablet", tablet, "front")):
        cameras[name].position = None
        browser.page.reload()
        cameras[name].wait_for(preset, timeout_s=60.0)
    wall.page.wait_for_timeout(3000)  # a late initial pose would reset the view: it must stay where it is
    assert (cameras["tablet"].looks_from(), cameras["wall"].looks_from()) == ("front", "oblique")
    assert cameras["wall"].moves == [], cameras["wall"].moves
    # viser's own preset buttons (the wall screen's panel, engineering on) turn the wall screen only.
    turn_engineering_on(wall.page)
    right = wall.page.frame_locator("#viz-frame").get_by_role("button", name="Right side")
    expect(right).to_be_visible(timeout=20_000)
    cameras["tablet"].moves.clear()
    right.evaluate("button => button.click()")  # a DOM click: software WebGL paints too seldom for pointers
    cameras["wall"].wait_for("right")
    tablet.page.wait_for_timeout(3000)
    assert (cameras["tablet"].moves, cameras["tablet"].looks_from()) == ([], "front"), cameras["tablet"].position
    assert not tablet.errors and not wall.errors, (tablet.errors, wall.errors)


def test_history_links_the_pdf_report_of_a_run(console: Any, clinic: dict[str, Any]) -> None:
    from pypdf import PdfReader

    session = console()
    page = session.login()
    page.get_by_role("link", name="Session history").click()
    link = page.get_by_role("link", name=f"PDF report (run {clinic['fall_run_id']})")
    expect(link).to_be_visible()
    response = page.request.get(clinic["base_url"] + link.get_attribute("href"))
    assert response.status == 200 and response.headers["content-type"] == "application/pdf"
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    (ARTIFACTS / "run-report.pdf").write_bytes(response.body())  # for a human look
    text = " ".join(" ".join(p.extract_text() for p in PdfReader(io.BytesIO(response.body())).pages).split())
    assert "Jürgen Äbischer" in text and "fall detected" in text and "harness load 412 N" in text, text[:2000]
    assert "25.0 s" in text, text[:2000]


def test_booking_conflicts_are_quoted_in_local_time(console: Any, clinic: dict[str, Any]) -> None:
    """The week shows and takes the clinic's wall time whatever the browser's zone (here Berlin), and a
    conflict is quoted in that same time, never in the browser's nor in UTC when the clinic is elsewhere."""
    import datetime as dt
    from zoneinfo import ZoneInfo

    session = console(timezone="Europe/Berlin")
    page = session.login()
    taken = dt.datetime.fromisoformat(clinic["booking"]["start"])
    local = taken.astimezone(ZoneInfo(clinic["booking"]["timezone"]))  # the clinic's zone
    session.go(f"#/schedule?week={local.date().isoformat()}")
    page.get_by_label("Patient", exact=True).select_option(str(clinic["patient"]["id"]))
    expect(page.get_by_label("Prescription").locator("option")).not_to_have_count(0)  # loaded for the patient
    page.get_by_label("Start").fill(local.strftime("%Y-%m-%dT%H:%M"))  # the same robot at the same time
    page.get_by_role("button", name="Book session").click()
    message = field_error(page, "Start")
    expect(message).to_contain_text(local.strftime("%H:%M"))  # clinic time, as the week shows it
    berlin = taken.astimezone(ZoneInfo("Europe/Berlin")).strftime("%H:%M")
    if berlin != local.strftime("%H:%M"):
        expect(message).not_to_contain_text(berlin)  # not the browser's clock


def test_dates_and_times_are_the_clinics_clock_on_every_page(console: Any, clinic: dict[str, Any]) -> None:
    """The week shows the clinic's wall time; the history, the session console and the patient's bookings
    show the same booking at the same time, not at the browser's (a laptop set to another zone)."""
    from zoneinfo import ZoneInfo

    session = console(timezone="America/New_York")
    page = session.login()
    taken = dt.datetime.fromisoformat(clinic["booking"]["start"])
    wall = taken.astimezone(ZoneInfo(clinic["booking"]["timezone"])).strftime("%I:%M %p")  # as en-US shows it
    browser = taken.astimezone(ZoneInfo("America/New_York")).strftime("%I:%M %p")
    assert wall != browser, "the test needs a clinic outside New York's zone"
    booked_row = page.get_by_role("row").filter(has=page.locator(f'a[href="#/session/{clinic["booking"]["id"]}"]'))
    pages = {
        "history": ("#/history", booked_row),
        "session console": (f"#/session/{clinic['booking']['id']}", page.locator("#main")),  # "Booked: ..."
        "patient profile": (f"#/patients/{clinic['patient']['id']}", booked_row),
    }
    for where, (route, shown) in pages.items():
        session.go(route)
        expect(shown, where).to_contain_text(wall)
        expect(shown, where).not_to_contain_text(browser)


def test_soap_notes_are_kept_per_run(console: Any, clinic: dict[str, Any]) -> None:
    session = console()
    page = session.login()
    session.go(f"#/session/{clinic['fall_booking']['id']}")
    panel = page.locator(f'#runs [data-run-id="{clinic["fall_run_id"]}"]')
    panel.get_by_text("Therapist notes (SOAP)").click()
    panel.get_by_label("S: subjective").fill("Felt unsteady after the turn.")
    panel.get_by_label("P: plan").fill("Repeat at 0.3 m/s² next week.")
    panel.get_by_role("button", name=re.compile("Save notes")).click()
    expect(panel.get_by_text("Notes saved")).to_be_visible()
    page.reload()
    panel.get_by_text("Therapist notes (SOAP)").click()
    expect(panel.get_by_label("S: subjective")).to_have_value("Felt unsteady after the turn.")
    expect(panel.get_by_label("P: plan")).to_have_value("Repeat at 0.3 m/s² next week.")


def test_a_patient_changed_meanwhile_is_not_overwritten(console: Any, clinic: dict[str, Any]) -> None:
    """Issue 20 defect 15: the edit form sends the version it read (If-Match); when a colleague saved in
    between, the page says who changed it and when, and nothing is written."""
    import httpx

    session = console(user=THERAPIST)
    page = session.login()
    created = httpx.post(f"{clinic['api']}/patients", headers={"Authorization": f"Bearer {clinic['admin_token']}"},
                         json={"identifier": "MRN-E2E-412", "name": "Otto Overwrite", "date_of_birth": "1960-01-01",
                               "sex": "male", "height_m": 1.75, "body_mass_kg": 75}, timeout=30).json()  # fmt: skip
    admin = {"Authorization": f"Bearer {clinic['admin_token']}"}
    therapist_id = httpx.get(f"{clinic['api']}/users", headers=admin, timeout=30).json()
    therapist_id = next(u["id"] for u in therapist_id if u["username"] == THERAPIST[0])
    httpx.post(f"{clinic['api']}/patients/{created['id']}/care-team", headers=admin, json={"user_id": therapist_id},
               timeout=30).raise_for_status()  # fmt: skip
    session.go(f"#/patients/{created['id']}/edit")
    page.get_by_label("Notes").fill("mine")
    colleague = httpx.patch(f"{clinic['api']}/patients/{created['id']}", headers={**admin, "If-Match": '"1"'},
                            json={"notes": "theirs"}, timeout=30)  # fmt: skip
    assert colleague.status_code == 200, colleague.text
    page.get_by_role("button", name="Save patient").click()
    refusal = page.locator(".banner.error")
    expect(refusal).to_contain_text(re.compile(r"Changed by e2e-admin at \d\d:\d\d( [AP]M)? \(now version 2\)"))
    expect(refusal).to_contain_text("Reload")
    stored = httpx.get(f"{clinic['api']}/patients/{created['id']}", headers=admin, timeout=30).json()
    assert stored["notes"] == "theirs"
