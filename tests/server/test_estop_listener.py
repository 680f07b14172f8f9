"""The stop listener's decisions without processes: which origins may stop, where the page sends its stop,
and the words of each unconfirmed answer (issue 20). The real processes: tests/server/test_estop_path.py."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from server.realtime.shm import ControlBlock, Seqlock
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


def test_a_stop_is_answered_while_the_listeners_log_cannot_be_written(tmp_path: Path) -> None:
    """Found by `bench faults --stop-under-load`: once a run, a stop took 250–350 ms from a requester that
    otherwise saw 4 ms, with the handshake and the worker's confirmation both fast. The listener wrote its
    request's log line to the log file before it answered, and the disk was busy with large exports. Here
    the log is a pipe that no one reads: once its buffer is full, every write waits, as a throttled file
    write does."""
    import fcntl
    import json
    import time

    import httpx

    paths = RobotPaths(tmp_path, "twin-1")
    paths.directory.mkdir(parents=True)  # as the robot daemon makes it
    read_end, write_end = os.pipe()
    fcntl.fcntl(write_end, 1031, 4096)  # F_SETPIPE_SZ: the smallest pipe buffer, one page
    listener = subprocess.Popen(
        [sys.executable, "-m", "server.robotd.estop_listener", "--robot", "twin-1", "--data-dir", str(tmp_path)],
        stdin=subprocess.DEVNULL, stdout=write_end, stderr=write_end,
    )  # fmt: skip
    os.close(write_end)
    try:
        published = address_file(paths)
        deadline = time.monotonic() + 60.0
        while not published.exists() and listener.poll() is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert published.exists(), "the listener did not publish its address"
        url = f"http://127.0.0.1:{json.loads(published.read_text())['port']}/estop"
        for click in range(100):  # each writes a log line or two: far more than the pipe holds
            try:
                answer = httpx.post(url, timeout=10.0)
            except httpx.TimeoutException:
                pytest.fail(f"stop {click + 1} was not answered within 10 s: the listener waits for its log")
            assert answer.status_code == 503, answer.text  # no robot daemon here: said at once
        listener.terminate()  # as its daemon ends it: it ends, whatever its log
        assert listener.wait(timeout=60.0) == 0
    finally:
        listener.kill()
        listener.wait()
        os.close(read_end)


def test_a_stop_and_its_audit_load_nothing(tmp_path: Path) -> None:
    """Found by `bench faults --stop-under-load`: the first stop of every run took 210–370 ms, the others 4 ms.
    The listener starts before the worker, so it attached the worker's blocks inside its first stop, and
    attaching loaded their compiled kernels (200 ms); the first stop's audit imported the daemon's message
    module (most of a second holding the interpreter lock: a stop arriving meanwhile waited); an
    unconfirmed stop imported the daemon's process module before it answered. Here the worker's blocks
    appear after the listener is built, as they do: its first stop and audit import and load nothing."""
    from server.realtime.telemetry import TELEMETRY_DTYPE

    paths = RobotPaths(tmp_path, "twin-1")
    paths.directory.mkdir(parents=True)
    probe = f"""
import sys, time
from pathlib import Path
from server.realtime import shm
from server.robotd.estop_listener import StopListener
from server.robotd.status import RobotPaths
from server.settings import Settings
listener = StopListener(Settings(data_dir=Path({str(tmp_path)!r})), RobotPaths(Path({str(tmp_path)!r}), "twin-1"))
print("built", flush=True)
sys.stdin.readline()  # the worker's blocks exist now
kernels = (shm.memory_barrier, shm._seqlock_try_read, shm._seqlock_write)
modules, loaded = set(sys.modules), [len(kernel.signatures) for kernel in kernels]
answer = listener.stop()  # attaches the blocks, latches; no worker confirms and no daemon runs
listener.audit(None, answer)  # no daemon to record it: logged
print(answer.outcome.name, sorted(set(sys.modules) - modules), loaded == [len(k.signatures) for k in kernels])
"""
    listener = subprocess.Popen([sys.executable, "-c", probe], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)  # fmt: skip
    control, state = ControlBlock(), Seqlock(TELEMETRY_DTYPE)
    try:
        assert listener.stdout is not None and listener.stdout.readline() == "built\n", listener.stderr
        paths.shared_memory.write_text(f"status-block {control.name} {state.name}\n")  # as the daemon lists them
        out, err = listener.communicate("go\n", timeout=120)
        assert listener.returncode == 0, err
        assert out == "NO_DAEMON [] True\n", out
    finally:
        listener.kill()
        control.close()
        state.close()
