"""Browser end-to-end fixtures: Debian's chromium (never a downloaded browser) and a real `ssp-rehab serve`
on free loopback ports with a temporary data directory and the simulator backend."""

from __future__ import annotations

import datetime as dt
import os
import re
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from benchmarks.fault_harness import stop_robot_daemon

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    # WebGL for the 3D view without a GPU: the software rasteriser must be allowed explicitly.
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
]
ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts" / "e2e"
ADMIN = ("e2e-admin", "e2e-password-1")
SERVICE_START_TIMEOUT_S = 300.0  # the worker compiles its kernels and builds the MuJoCo model at start


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _cli() -> list[str]:
    return [sys.executable, "-m", "server.cli.main"]


@pytest.fixture(scope="session")
def chromium_path() -> Path:
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent: install Debian's chromium package to run the browser tests")
    return CHROMIUM


@pytest.fixture(scope="session")
def console_service(tmp_path_factory: pytest.TempPathFactory, chromium_path: Path) -> Iterator[dict[str, object]]:
    data_dir = tmp_path_factory.mktemp("e2e-data")
    port, viz_port = free_port(), free_port()
    env = {
        **os.environ,
        "SSP_REHAB_VIZ_PORT": str(viz_port),
        "SSP_REHAB_DATA_DIR": str(data_dir),
        # A shared 2-core CI machine cannot hold 1 kHz beside a browser; the flow under test is the console's.
        "SSP_REHAB_CONTROL_RATE_HZ": os.environ.get("SSP_REHAB_E2E_CONTROL_RATE_HZ", "250"),
    }
    root = Path(__file__).resolve().parents[2]
    subprocess.run(
        [*_cli(), "create-user", "--username", ADMIN[0], "--password", ADMIN[1], "--role", "admin",
         "--data-dir", str(data_dir)],
        check=True, cwd=root, env=env, capture_output=True,
    )  # fmt: skip
    backend = os.environ.get("SSP_REHAB_E2E_BACKEND", "kinematic")
    log = (data_dir / "serve.log").open("w")
    process = subprocess.Popen(
        [*_cli(), "serve", "--port", str(port), "--data-dir", str(data_dir), "--backend", backend],
        cwd=root, env=env, stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    base_url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + SERVICE_START_TIMEOUT_S
    try:
        while True:
            if process.poll() is not None:
                raise RuntimeError(
                    f"ssp-rehab serve exited ({process.returncode}): {(data_dir / 'serve.log').read_text()[-3000:]}"
                )
            try:
                health = httpx.get(f"{base_url}/api/v1/health", timeout=2.0)
                if health.status_code == 200 and health.json()["robot_connected"]:
                    break  # the robot daemon is ready too: every test starts from a ready robot
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"ssp-rehab serve did not answer within {SERVICE_START_TIMEOUT_S} s")
            time.sleep(0.5)
        yield {
            "base_url": base_url,
            "viz_port": viz_port,
            "backend": backend,
            "log": data_dir / "serve.log",
            "database_url": f"sqlite:///{(data_dir / 'ssp-rehab.sqlite3').resolve()}",
        }
    finally:
        process.terminate()
        try:
            process.wait(60)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)
        stop_robot_daemon(data_dir)  # if serve was killed before it could stop its daemon
        log.close()
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "serve.log").write_text((data_dir / "serve.log").read_text())


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[pytest.TestReport]:
    """Keeps each phase's report on the test item, so fixtures can save a screenshot when a test failed."""
    report = yield
    setattr(item, f"rep_{report.when}", report)
    return report


# --- a seeded clinic and logged-in browser contexts, shared by the browser tests (issue 16) ---------------

# The widths of ordinary laptops and desktops (issue 16, build §1).
VIEWPORTS = [(1024, 768), (1280, 800), (1366, 768), (1920, 1080)]
# A long therapist name widens the top bar: the emergency stop must stay whole beside it.
THERAPIST = ("e2e-therapist", "e2e-password-2", "Dr. Maximiliane Mustermann-Schöneberg, PT")
FALL_ROBOT = "twin-fall"  # the seeded fall run's robot, so the other flows' robot stays startable


@pytest.fixture(scope="session")
def clinic(console_service: dict[str, Any]) -> dict[str, Any]:
    """Records made through the API: a therapist with a long name, a patient, a prescription, a booking,
    and a second booking whose run ended in a detected fall (written as the recorder writes it)."""
    base = f"{console_service['base_url']}/api/v1"
    admin = _token(base, *ADMIN)
    headers = {"Authorization": f"Bearer {admin}"}
    with httpx.Client(base_url=base, headers=headers, timeout=30) as api:
        therapist = api.post("/users", json={"username": THERAPIST[0], "password": THERAPIST[1], "role": "therapist",
                                             "full_name": THERAPIST[2]}).json()  # fmt: skip
        long_named = api.post("/patients", json={  # a long name widens the booking form's patient list
            "identifier": "MRN-DEF-LONG-000001", "name": "Maria-Magdalena Schönhausen-Wittgenstein",
            "date_of_birth": "1944-09-30", "sex": "female", "height_m": 1.6, "body_mass_kg": 58,
        }).json()  # fmt: skip
        patient = api.post("/patients", json={
            "identifier": "MRN-DEF-1", "name": "Jürgen Äbischer", "date_of_birth": "1950-02-03", "sex": "male",
            "height_m": 1.82, "body_mass_kg": 80, "notes": "prefers the left rail at entry",
        }).json()  # fmt: skip
        for record in (long_named, patient):  # the therapist treats both (docs/service.md, care teams)
            api.post(f"/patients/{record['id']}/care-team", json={"user_id": therapist["id"]}).raise_for_status()
        prescription = api.post("/prescriptions", json={
            "patient_id": patient["id"], "name": "Sway basics",
            "segments": [{"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.4, "frequency_hz": 0.5},
                          "duration_s": 20}],
        }).json()  # fmt: skip
        start = dt.datetime.now(dt.UTC).replace(microsecond=0) + dt.timedelta(hours=2)
        booking = api.post("/sessions", json={
            "patient_id": patient["id"], "prescription_id": prescription["id"], "robot": "twin-1",
            "start": start.isoformat(), "duration_s": 1800,
        }).json()[0]  # fmt: skip
        fall_booking = api.post("/sessions", json={
            "patient_id": patient["id"], "prescription_id": prescription["id"], "robot": FALL_ROBOT,
            "start": (start + dt.timedelta(hours=1)).isoformat(), "duration_s": 1800,
        }).json()[0]  # fmt: skip
    fall_run_id = _seed_fall_run(str(console_service["database_url"]), fall_booking)
    return {"base_url": console_service["base_url"], "api": base, "admin_token": admin, "patient": patient,
            "prescription": prescription, "booking": booking, "fall_booking": fall_booking,
            "fall_run_id": fall_run_id}  # fmt: skip


def _token(base: str, username: str, password: str) -> str:
    response = httpx.post(f"{base}/auth/login", json={"username": username, "password": password}, timeout=30)
    response.raise_for_status()
    return str(response.json()["access_token"])


def _seed_fall_run(database_url: str, booking: dict[str, Any]) -> int:
    """A run that ended in a fall, as the session recorder writes it (run + the worker's fall event)."""
    from sqlalchemy import select

    from server.db import Database, create_database_engine, load_models
    from server.prescriptions.models import PrescriptionVersion
    from server.robotd.models import SessionEvent, SessionRun

    load_models()
    engine = create_database_engine(database_url)
    try:
        with Database(engine).session() as session:
            version = session.scalars(
                select(PrescriptionVersion).where(PrescriptionVersion.prescription_id == booking["prescription_id"])
            ).first()
            assert version is not None
            now = dt.datetime.now(dt.UTC)
            run = SessionRun(scheduled_session_id=booking["id"], prescription_version_id=version.id,
                             robot=booking["robot"], state="ended", outcome="fall",
                             started_at=now - dt.timedelta(seconds=40), ended_at=now)  # fmt: skip
            session.add(run)
            session.flush()
            start = now - dt.timedelta(seconds=25)
            session.add(SessionEvent(run_id=run.id, kind="start", tick=1250, tick_time_s=5.0, utc=start,
                                     detector="console", details={}))  # fmt: skip
            session.add(SessionEvent(run_id=run.id, kind="fall", tick=7500, tick_time_s=30.0, utc=now,
                                     detector="harness_load",
                                     details={"harness_load_n": 412.0, "threshold_n": 300.0}))  # fmt: skip
            session.commit()
            return int(run.id)
    finally:
        engine.dispose()


@pytest.fixture(scope="session")
def browser(chromium_path: Path) -> Iterator[Any]:
    sync_api = pytest.importorskip("playwright.sync_api")
    # expect()'s own default is 5 s: a preview or a save on a loaded 2-core machine takes longer.
    sync_api.expect.set_options(timeout=20_000)
    with sync_api.sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=str(chromium_path), headless=True, args=CHROMIUM_ARGS)
        yield launched
        launched.close()


class Console:
    """One browser context logged in through the login page, with JavaScript errors collected."""

    def __init__(self, browser: Any, base_url: str, name: str, *, user: tuple[str, ...] = ADMIN,
                 viewport: tuple[int, int] = (1280, 800), offline: bool = False,
                 timezone: str | None = None) -> None:  # fmt: skip
        self.base_url, self.name = base_url, name
        self.context = browser.new_context(viewport={"width": viewport[0], "height": viewport[1]}, timezone_id=timezone)
        if offline:  # everything but this service is unreachable: no CDN, no fonts
            self.context.route(re.compile(r"^https?://(?!127\.0\.0\.1[:/])"), lambda route: route.abort())
        self.page = self.context.new_page()
        self.page.set_default_timeout(20_000)
        self.errors: list[str] = []
        self.page.on("pageerror", lambda error: self.errors.append(str(error)))
        self.user = user

    def login(self) -> Any:
        self.page.goto(f"{self.base_url}/#/login")
        self.page.get_by_label("Username").fill(self.user[0])
        self.page.get_by_label("Password").fill(self.user[1])
        self.page.get_by_role("button", name="Log in").click()
        from playwright.sync_api import expect

        expect(self.page.get_by_role("heading", name="Patients")).to_be_visible()
        return self.page

    def go(self, route: str) -> Any:
        self.page.goto(f"{self.base_url}/{route}")
        return self.page

    def close(self, failed: bool) -> None:
        if failed:
            ARTIFACTS.mkdir(parents=True, exist_ok=True)
            try:  # a starved renderer (software WebGL on a loaded machine) may not paint in time
                self.page.screenshot(path=str(ARTIFACTS / f"defect-{self.name}.png"), full_page=True, timeout=15_000)
            except Exception as error:
                (ARTIFACTS / f"defect-{self.name}.txt").write_text(f"no screenshot: {error}")
        self.context.close()


@pytest.fixture
def console(browser: Any, clinic: dict[str, Any], request: pytest.FixtureRequest) -> Iterator[Any]:
    opened: list[Console] = []

    def open_console(**options: Any) -> Console:
        made = Console(browser, clinic["base_url"], f"{request.node.name}-{len(opened)}", **options)
        opened.append(made)
        return made

    yield open_console
    failed = bool(getattr(request.node, "rep_call", None) and request.node.rep_call.failed)
    for made in opened:
        made.close(failed)


def fill_patient(
    page: Any, identifier: str, name: str, born: str, sex: str | None, height_cm: str, mass_kg: str
) -> None:
    """Fills the new-patient form (sex None: left unchosen)."""
    page.get_by_label("Record number").fill(identifier)
    page.get_by_label("Name").fill(name)
    page.get_by_label("Date of birth").fill(born)
    if sex is not None:
        page.get_by_label("Sex").select_option(sex)
    page.get_by_label("Height").fill(height_cm)
    page.get_by_label("Body mass").fill(mass_kg)


def field_error(page: Any, label: str) -> Any:
    """The message shown beside the field with this label."""
    return page.locator(".field:has(#" + page.get_by_label(label).get_attribute("id") + ") .field-error")


def turn_engineering_on(page: Any) -> None:
    """Ticks the top bar's engineering switch. A DOM click: with the 3D view rendering in software on a
    loaded machine, Playwright's pointer actions wait for animation frames that come too seldom."""
    from playwright.sync_api import expect

    page.evaluate("() => { const box = document.getElementById('engineering-switch'); if (!box.checked) box.click(); }")
    expect(page.get_by_label("Engineering details")).to_be_checked()


ROBOT_RESET_TIMEOUT_S = 60.0


def reset_latched_stop(clinic: dict[str, Any]) -> None:
    """Clears a latched emergency stop so that the next test finds a startable robot (a reset never moves it)."""
    headers = {"Authorization": f"Bearer {clinic['admin_token']}"}
    deadline = time.monotonic() + ROBOT_RESET_TIMEOUT_S
    while time.monotonic() < deadline:
        state = httpx.get(f"{clinic['api']}/robot/state", headers=headers, timeout=30).json()
        if not state.get("estop_latched") and state.get("state") != "estop":
            return
        httpx.post(f"{clinic['api']}/robot/reset", headers=headers, timeout=30)
        time.sleep(0.5)
    raise AssertionError(f"the robot did not leave its emergency stop within {ROBOT_RESET_TIMEOUT_S} s")


def acknowledge_earlier_stop(clinic: dict[str, Any]) -> None:
    """An earlier browser test's run on the shared robot may have ended with a stop: its latch is reset and the
    stop, which keeps Start disabled until then, acknowledged, as its therapist would. A test that failed
    midway then leaves the next one a startable robot."""
    reset_latched_stop(clinic)
    headers = {"Authorization": f"Bearer {clinic['admin_token']}"}
    with httpx.Client(base_url=clinic["api"], headers=headers, timeout=60) as api:
        leftover = api.get("/reviews/pending", params={"robot": "twin-1"}).json()
        if leftover is not None:
            api.post(f"/runs/{leftover['run_id']}/acknowledge", json={"note": "e2e: an earlier test's stop"})
