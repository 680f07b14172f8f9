"""Issue 21, defect 10 and build 8 (lifetimes): a `serve` that started its robot daemon stops it when it
exits (Ctrl-C), after a controlled stop of a run in motion and with the records flushed, unless told
`--keep-robot`; a daemon that already ran when `serve` started is never stopped by it. Real processes;
every wait is event-based and generous (a loaded 2-core machine)."""

from __future__ import annotations

import signal
from collections.abc import Iterator
from pathlib import Path

import pytest
from sqlalchemy import text

from benchmarks.fault_harness import EVENT_TIMEOUT_S, Console, alive, wait_for
from server.realtime.telemetry import SupervisorState
from server.robotd.records import decode_chunk
from server.robotd.status import RobotPaths, daemon_running

pytestmark = pytest.mark.slow

EXIT_TIMEOUT_S = 300.0  # serve waits for its daemon's controlled stop and flush; generous on a loaded machine


@pytest.fixture
def consoles(tmp_path: Path) -> Iterator[list[Console]]:
    """The consoles a test starts; each is stopped afterwards, and so is any daemon left in its data dir."""
    started: list[Console] = []
    try:
        yield started
    finally:
        for console in started:
            console.stop()


def start(consoles: list[Console], data_dir: Path, *serve_args: str) -> Console:
    console = Console(data_dir, serve_args=serve_args)
    consoles.append(console)
    console.start()
    return console


def ctrl_c(console: Console, signum: int = signal.SIGINT) -> str:
    """SIGINT to `serve` (what Ctrl-C sends it; systemd sends SIGTERM), then its whole output once it exited."""
    assert console.process is not None
    console.signal(signum)
    console.process.wait(EXIT_TIMEOUT_S)
    console.process = None
    return console.log_text()


def daemon_gone(console: Console, pid: int) -> None:
    paths = RobotPaths(console.data_dir.resolve(), console.robot)
    wait_for(
        lambda: not alive(pid) and not daemon_running(paths),
        EXIT_TIMEOUT_S,
        f"the robot daemon (pid {pid}) that serve started to end and release its lock",
        0.1,
    )


@pytest.mark.parametrize(
    ("workers", "signum"),
    [("1", signal.SIGINT), ("2", signal.SIGINT), ("1", signal.SIGTERM)],
    ids=["ctrl-c", "ctrl-c-two-web-processes", "sigterm"],
)
def test_defect_10_ctrl_c_on_serve_stops_the_robot_daemon_it_started(
    consoles: list[Console], tmp_path: Path, workers: str, signum: int
) -> None:
    """With several web processes, whichever of them started the daemon, `serve` stops it once, at its end."""
    console = start(consoles, tmp_path / "console", "--workers", workers)
    daemon = console.daemon_pid()
    assert daemon is not None and alive(daemon)
    output = ctrl_c(console, signum)
    daemon_gone(console, daemon)
    assert f"stopped the robot daemon {console.robot} that this console started" in output, output[-3000:]


def test_keep_robot_leaves_the_daemon_and_a_daemon_that_already_ran_is_never_stopped(
    consoles: list[Console], tmp_path: Path
) -> None:
    data_dir = tmp_path / "console"
    first = start(consoles, data_dir, "--keep-robot")
    daemon = first.daemon_pid()
    assert daemon is not None
    output = ctrl_c(first)
    # serve has exited: whatever it was going to do to the daemon is done.
    assert alive(daemon) and first.daemon_pid() == daemon, output[-3000:]
    assert f"left the robot daemon {first.robot} running (--keep-robot)" in output, output[-3000:]
    assert f"kill -TERM {daemon}" in output, output[-3000:]

    second = start(consoles, data_dir)  # attaches to the daemon that was already running
    assert second.daemon_pid() == daemon
    output = ctrl_c(second)
    assert alive(daemon) and second.daemon_pid() == daemon, output[-3000:]
    assert "this console did not start it" in output, output[-3000:]
    second.stop_daemon()
    daemon_gone(second, daemon)


def test_a_run_in_motion_when_serve_exits_ends_interrupted_with_a_controlled_stop_and_its_records(
    consoles: list[Console], tmp_path: Path
) -> None:
    console = start(consoles, tmp_path / "console")
    daemon = console.daemon_pid()
    assert daemon is not None
    started = console.post(f"/sessions/{console.book()}/start")
    assert started.status_code == 200, started.text
    run_id = int(started.json()["id"])
    console.wait_moving()
    wait_for(lambda: console.run(run_id)["sample_count"] > 0, EVENT_TIMEOUT_S, "the run to record samples", 0.1)
    output = ctrl_c(console)
    daemon_gone(console, daemon)
    run = console.run_row(run_id)
    assert (run["state"], run["outcome"]) == ("ended", "interrupted"), run
    assert f"run {run_id} interrupted with a controlled stop; records flushed" in output, output[-3000:]
    samples, first_tick, last_tick = console.telemetry_ticks(run_id)
    assert samples > 0 and last_tick > first_tick, (samples, first_tick, last_tick)
    with console.database() as connection:
        blob = connection.execute(
            text("SELECT data FROM telemetry_chunks WHERE run_id = :r ORDER BY sequence DESC LIMIT 1"), {"r": run_id}
        ).scalar_one()
    last_state = SupervisorState(int(decode_chunk(blob)["state"][-1]))
    # The recording went on into the controlled stop (not an emergency stop or a fault).
    assert last_state in (SupervisorState.STOPPING, SupervisorState.STOPPED), last_state
