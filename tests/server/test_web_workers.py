"""Issue 15 §2: `ssp-rehab serve --workers 2` — two web processes behind one port, one robot daemon, one
session-control lease, one token store. Real processes and real HTTP; every wait is event-based.

A keep-alive `httpx.Client` stays on the web process that accepted its connection; `/health` names that
process (`web_pid`), so each request below is sent, and checked, on a known process."""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from benchmarks.fault_harness import ADMIN, EVENT_TIMEOUT_S, START_TIMEOUT_S, Console, alive, descendants, wait_for

WEB_PROCESSES = 2


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Console]:
    """One `serve --workers 2` for the module: its tests leave every process of it running."""
    instance = Console(tmp_path_factory.mktemp("web-workers") / "console", serve_args=("--workers", str(WEB_PROCESSES)))
    instance.start()
    try:
        yield instance
    finally:
        instance.stop()


def web_pid(client: httpx.Client) -> int:
    return int(client.get("/health").json()["web_pid"])


class Process:
    """Requests to one web process: a keep-alive connection to it, opened again (until the kernel hands a
    new connection to that process) when uvicorn closed an idle one."""

    def __init__(self, console: Console, pid: int) -> None:
        self.console, self.pid = console, pid
        self.client = self._connect()

    def _connect(self) -> httpx.Client:
        return httpx.Client(base_url=self.console.url, headers=self.console.headers(), timeout=300.0)

    def _on_this_process(self) -> bool:
        if web_pid(self.client) == self.pid:
            return True
        self.client.close()
        self.client = self._connect()
        return False

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        wait_for(self._on_this_process, EVENT_TIMEOUT_S, f"a connection to web process {self.pid}", 0.01)
        response = self.client.request(method, path, **kwargs)
        assert web_pid(self.client) == self.pid, "the keep-alive connection moved to another process"
        return response

    def close(self) -> None:
        self.client.close()


@contextlib.contextmanager
def each_process(console: Console) -> Iterator[list[Process]]:
    """Every web process (by pid order), once each has said that the robot is ready."""
    ready: set[int] = set()

    def both_ready() -> bool:
        health = httpx.get(f"{console.url}/health", timeout=60.0).json()  # a new connection each time
        if health["robot_connected"]:
            ready.add(int(health["web_pid"]))
        return len(ready) == WEB_PROCESSES

    wait_for(both_ready, START_TIMEOUT_S, "both web processes to answer with the robot ready", 0.05)
    processes = [Process(console, pid) for pid in sorted(ready)]
    try:
        yield processes
    finally:
        for process in processes:
            process.close()


def robot_daemons(console: Console) -> list[int]:
    assert console.process is not None
    return [
        pid
        for pid in descendants(console.process.pid)
        if alive(pid) and b"\x00robot\x00--robot\x00" in Path(f"/proc/{pid}/cmdline").read_bytes()
    ]


@pytest.mark.slow
def test_two_web_processes_share_one_daemon_and_one_lease(console: Console) -> None:
    """Issue 20 defect 19: the web processes of one `serve` are one console. Before, a start on the idle
    robot that landed on the process that had not started the last run was refused (409 "another console
    (process N) holds the session control"): 5 of 8 starts. Another `serve` is still refused (test_faults)."""
    with each_process(console) as (first, other):
        # Both processes raced to start the daemon at start-up; the daemon's lock left exactly one.
        daemons = wait_for(lambda: len(d := robot_daemons(console)) == 1 and d, EVENT_TIMEOUT_S, "one robot daemon")
        assert daemons == [console.daemon_pid()], (daemons, console.daemon_pid())

        for process in (first, other, first):
            wait_for(
                lambda process=process: (
                    process.request("GET", "/robot/state").json().get("state") in ("stopped", "idle")
                ),
                EVENT_TIMEOUT_S,
                "the robot to stand still",
            )
            started = process.request("POST", f"/sessions/{console.book()}/start")
            assert started.status_code == 200, f"process {process.pid}: {started.text}"
            stopped = process.request("POST", f"/sessions/{started.json()['scheduled_session_id']}/stop")
            assert stopped.status_code == 200, stopped.text
            wait_for(
                lambda run_id=started.json()["id"]: console.run(run_id)["state"] == "ended",
                EVENT_TIMEOUT_S,
                "the run to end",
                0.1,
            )
    # Each web process logs (JSON lines, as one process does), e.g. its own start-up.
    started_up = [line for line in console.log_text().splitlines() if '"Application startup complete."' in line]
    assert len(started_up) == WEB_PROCESSES, console.log_text()[-3000:]


@pytest.mark.slow
def test_a_token_revoked_through_one_process_is_refused_by_the_other(console: Console) -> None:
    with each_process(console) as (first, second):
        login = first.request("POST", "/auth/login", json={"username": ADMIN[0], "password": ADMIN[1]})
        assert login.status_code == 200, login.text
        token = {"Authorization": f"Bearer {login.json()['access_token']}"}
        assert second.request("GET", "/auth/me", headers=token).status_code == 200
        assert first.request("POST", "/auth/logout", headers=token).status_code == 204
        refused = second.request("GET", "/auth/me", headers=token)
        assert refused.status_code == 401, f"process {second.pid} still accepts the revoked token: {refused.text}"


def test_the_web_processes_get_the_options_and_one_signing_key(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from server.app import app_from_environment
    from server.cli.service_commands import _prepare_web_processes, _settings

    data_dir = tmp_path / "data"
    options: dict[str, Any] = {"data_dir": data_dir, "backend": "kinematic", "robot": "twin-7", "start_worker": False}
    for name in ("DATA_DIR", "BACKEND", "ROBOT", "START_WORKER", "DATABASE_URL", "SECRET_KEY", "ROBOT_FILE"):
        # setenv first so that monkeypatch restores (or removes) what `_prepare_web_processes` writes.
        monkeypatch.setenv(f"SSP_REHAB_{name}", "")
        monkeypatch.delenv(f"SSP_REHAB_{name}")
    monkeypatch.setenv("SSP_REHAB_VIZ_ENABLED", "false")
    factory = _prepare_web_processes(_settings(**options), options)
    assert factory == "server.app:app_from_environment"
    key = (data_dir / "secret_key").read_bytes()
    assert key, "the signing key must exist before the processes start"
    assert (data_dir / "ssp-rehab.sqlite3").exists(), "the schema is upgraded once, before the processes"
    settings = app_from_environment().state.settings  # what each web process builds
    assert (settings.data_dir, settings.backend, settings.robot, settings.start_worker) == (
        data_dir.resolve(),
        "kinematic",
        "twin-7",
        False,
    )
    assert settings.resolved_secret_key() == key.strip()


def test_a_console_whose_daemon_lost_the_start_race_says_starting_not_absent(tmp_path: Path) -> None:
    """Two web processes start at once: both spawn a daemon, the lock admits one, the other exits
    "already running". The console whose daemon exited has no link yet while the winner warms up:
    it says "starting" (the robot's lock is held), never "no robot daemon"."""
    from server.robotd.link import DaemonLink
    from server.robotd.process import take_lock
    from server.robotd.status import DaemonState, RobotPaths

    paths = RobotPaths(tmp_path, "twin-1")
    lost_the_race = subprocess.Popen([sys.executable, "-c", "raise SystemExit(1)"])
    lost_the_race.wait(60)
    link = DaemonLink(paths, spawned=lost_the_race)  # not opened: no link to the winner yet
    assert link.status().state == DaemonState.ABSENT  # no daemon holds the lock
    winner_lock = take_lock(paths)  # the winning daemon holds it (another open file: flock is per file)
    try:
        status = link.status()
        assert status.state == DaemonState.STARTING, status
        assert "another" in status.reason, status
    finally:
        os.close(winner_lock)
    assert link.status().state == DaemonState.ABSENT


@pytest.mark.parametrize("workers", ["0", "17"])
def test_a_number_of_web_processes_out_of_range_is_refused_naming_it(workers: str) -> None:
    from typer.testing import CliRunner

    from server.cli.main import app

    result = CliRunner().invoke(app, ["serve", "--workers", workers, "--no-robot"])
    assert result.exit_code != 0
    assert f"--workers = {workers}: must be from 1 to 16" in result.output, result.output
