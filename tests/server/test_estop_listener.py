"""The stop listener's decisions without processes: which origins may stop, where the page sends its stop,
and the words of each unconfirmed answer (issue 20). The real processes: tests/server/test_estop_path.py."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from server.realtime.shm import ControlBlock
from server.robotd import estop
from server.robotd.estop_listener import OriginCheck, address_file, page_stop_url
from server.robotd.status import RobotPaths
from server.settings import Settings


@pytest.fixture
def settings(tmp_path: Path) -> Settings:
    return Settings(data_dir=tmp_path, console_port=8000, allowed_origins=["https://rehab.example"])


@pytest.mark.parametrize(
    ("origin", "host", "allowed"),
    [
        (None, "127.0.0.1:8001", True),  # a script: no Origin
        ("http://127.0.0.1:8000", "127.0.0.1:8001", True),  # the console's page, direct
        ("http://rehab.local", "rehab.local", True),  # the page's own origin, behind a proxy
        ("https://rehab.example", "127.0.0.1:8001", True),  # configured
        ("http://127.0.0.1:9999", "127.0.0.1:8001", False),  # another port of the same host
        ("http://evil.example:8000", "127.0.0.1:8001", False),
        ("null", "127.0.0.1:8001", False),
        ("file://", "127.0.0.1:8001", False),
    ],
)
def test_only_the_consoles_origin_may_stop(settings: Settings, origin: str | None, host: str, allowed: bool) -> None:
    assert OriginCheck(settings).allowed(origin, host) is allowed


def test_the_page_learns_the_listeners_address(settings: Settings) -> None:
    paths = RobotPaths(settings.data_dir, "twin-1")
    assert page_stop_url(settings, paths, "127.0.0.1:8000", "http") is None  # no listener yet
    paths.directory.mkdir(parents=True)
    address_file(paths).write_text('{"port": 8123, "host": "127.0.0.1", "pid": 1}')
    assert page_stop_url(settings, paths, "console.local:8000", "http") == "http://console.local:8123/estop"
    assert page_stop_url(settings, paths, "[::1]:8000", "http") == "http://[::1]:8123/estop"
    assert page_stop_url(settings, paths, "console.local", "https") is None  # mixed content: the web route
    proxied = settings.model_copy(update={"estop_public_url": "/estop"})
    assert page_stop_url(proxied, paths, "console.local", "https") == "/estop"


def test_no_robot_process_only_when_the_process_is_gone() -> None:
    assert estop.unconfirmed(False, None, "why", 0.25).outcome is estop.StopOutcome.NO_DAEMON
    assert estop.unconfirmed(True, None, "why", 0.25).outcome is estop.StopOutcome.NO_WORKER
    control = ControlBlock()
    try:
        control.fields["worker_pid"] = os.getpid()  # alive: slow, not gone
        slow = estop.unconfirmed(True, control, "why", 0.25)
        assert slow.outcome is estop.StopOutcome.NOT_CONFIRMED and slow.http_status == 504
        assert "requested, not confirmed within 250 ms" in slow.detail and "no robot process" not in slow.detail
        ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
        control.fields["worker_pid"] = int(ended.stdout)  # a process that has ended
        gone = estop.unconfirmed(True, control, "why", 0.25)
        assert gone.outcome is estop.StopOutcome.NO_DAEMON and gone.http_status == 503
        assert gone.detail.startswith(estop.NO_ROBOT_PROCESS)
    finally:
        control.close()
