"""Issue 20, defects 3 and 18, against a real console (`serve`, its robot daemon and worker as processes):
a data disk that fills mid-session, and a worker or a daemon killed with SIGKILL.

Every wait is event-based and generous; the latency targets are measured by `ssp-rehab bench faults`.
"""

from __future__ import annotations

import datetime as dt
import errno
import json
import os
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from benchmarks.fault_harness import (
    EVENT_TIMEOUT_S,
    SHORT_SINE,
    START_TIMEOUT_S,
    Console,
    alive,
    descendants,
    fill_disk,
    small_disk,
    wait_for,
)

pytestmark = pytest.mark.slow

DISK_MB = 48  # the database, the logs and a few seconds of journal; the filler takes the rest
LONG_SESSION = [{"cue": SHORT_SINE, "duration_s": 300.0}]


def start_ok(console: Console, session_id: int) -> dict[str, Any]:
    response = console.post(f"/sessions/{session_id}/start")
    assert response.status_code == 200, response.text
    return dict(response.json())


def samples_grow(console: Console, run_id: int, beyond: int) -> None:
    wait_for(
        lambda: console.run_row(run_id)["sample_count"] > beyond,
        EVENT_TIMEOUT_S,
        f"run {run_id} to record more than {beyond} samples",
        0.1,
    )


def details_of(event: dict[str, Any]) -> dict[str, Any]:
    details = event["details"]
    return dict(details if isinstance(details, dict) else json.loads(details))


def utc_s(value: object) -> float:
    parsed = value if isinstance(value, dt.datetime) else dt.datetime.fromisoformat(str(value))
    return (parsed if parsed.tzinfo else parsed.replace(tzinfo=dt.UTC)).timestamp()


def robot_state(console: Console) -> dict[str, Any]:
    response = console.get("/robot/state")
    return dict(response.json()) if response.status_code == 200 else {}


def wait_run_ended(console: Console, run_id: int, timeout_s: float = EVENT_TIMEOUT_S) -> dict[str, Any]:
    row = wait_for(
        lambda: (r := console.run_row(run_id))["state"] == "ended" and r, timeout_s, f"run {run_id} to end", 0.1
    )
    return dict(row)


def assert_every_sample_kept(console: Console, run_id: int) -> None:
    """No gap inside the recorded span, the count agrees, and the span reaches the drives' stop."""
    events = console.events(run_id)
    disabled = [e for e in events if e["kind"] == "drives_disabled"]
    assert disabled, f"the stop's drives_disabled was not recorded: {[e['kind'] for e in events]}"
    stored, first, last = console.telemetry_ticks(run_id)
    assert stored == last - first + 1, f"{last - first + 1 - stored} samples lost between ticks {first} and {last}"
    assert last >= disabled[0]["tick"], f"telemetry ends at tick {last}, before the drives were off"
    assert console.run_row(run_id)["sample_count"] == stored


# --- defect 3: a full data disk --------------------------------------------------------------------------


@pytest.fixture
def console_on_small_disk(tmp_path: Path) -> Iterator[Console]:
    """A console whose whole data directory is on a tmpfs of DISK_MB (as root; skipped otherwise)."""
    try:
        with small_disk(tmp_path / "small-disk", DISK_MB) as disk:
            instance = Console(disk / "console")
            instance.start()
            try:
                yield instance
            finally:
                instance.stop()
    except PermissionError as error:
        pytest.skip(str(error))


def test_defect_3_a_full_data_disk_stops_the_run_and_keeps_every_sample(console_on_small_disk: Console) -> None:
    console = console_on_small_disk
    run = start_ok(console, console.book(segments=LONG_SESSION))
    run_id = run["id"]
    console.wait_moving()
    samples_grow(console, run_id, 1000)
    journal = console.data_dir / "runs" / console.robot / f"run-{run_id}"
    filler = fill_disk(console.data_dir)
    try:
        stopped = wait_for(
            lambda: (s := robot_state(console)).get("state") in ("stopping", "stopped") and s,
            EVENT_TIMEOUT_S,
            "the robot to stop after its recorder could not write",
            0.05,
        )
        assert not stopped["estop_latched"], f"a controlled stop was expected, not an emergency stop: {stopped}"
        assert stopped["stop_reason"] == "recording_failed", stopped
        health = console.health()
        assert health["status"] == "degraded", health
        reason = str(health["recording"]["reason"])
        assert "No space left on device" in reason and str(journal) in reason, health
        assert journal.is_dir(), "the journal was deleted while the database could not take its contents"
    finally:
        filler.unlink()
    ended = wait_run_ended(console, run_id)
    assert ended["outcome"] == "interrupted", ended
    expected = {"recording_failed", "controlled_stop", "drives_disabled", "run_ended"}
    wait_for(
        lambda: expected <= {e["kind"] for e in console.events(run_id)},
        EVENT_TIMEOUT_S,
        f"the run's {sorted(expected)} events",
        0.1,
    )
    events = console.events(run_id)
    failed = details_of(next(e for e in events if e["kind"] == "recording_failed"))
    assert failed["errno"] == errno.ENOSPC and failed["error"] == "ENOSPC" and str(journal) in failed["path"], failed
    stop = next(e for e in events if e["kind"] == "controlled_stop")
    assert details_of(stop)["reason"] == "recording_failed", stop
    # The target (1 s) is measured by `bench faults`; here only that the stop followed the failure.
    failed_at = utc_s(next(e for e in events if e["kind"] == "recording_failed")["utc"])
    assert 0.0 <= utc_s(stop["utc"]) - failed_at < 10.0, (failed_at, stop["utc"])
    wait_for(lambda: not journal.exists(), EVENT_TIMEOUT_S, "the journal to go once the database holds the run")
    assert_every_sample_kept(console, run_id)
    wait_for(lambda: console.health()["status"] == "ok", EVENT_TIMEOUT_S, "/health to be ok once there is space")
    assert console.post("/robot/reset").status_code == 200
    assert console.acknowledge_pending() == run_id  # the stop moved the patient: acknowledged before a start
    start_ok(console, console.book())


# --- defect 18: a dead worker or daemon -------------------------------------------------------------------


def worker_pids(console: Console) -> list[int]:
    return [int(details_of(e)["pid"]) for e in console.events() if e["kind"] == "worker_started"]


def assert_reset_needed_then_free(console: Console, reason: str) -> None:
    """The fresh worker shows the stop (drives off) until a therapist resets; then a new session starts."""
    state = robot_state(console)
    assert state.get("state") == "fault" and state.get("stop_reason") == reason, state
    refused = console.post(f"/sessions/{console.book()}/start")
    assert refused.status_code != 200, "a new session started before anyone reset the robot"
    reset = console.post("/robot/reset")
    assert reset.status_code == 200, reset.text
    console.acknowledge_pending()  # the interrupted run (build 9), when the loss ended one
    start_ok(console, console.book())
    console.wait_moving()
    estop = console.post("/estop")  # the web side's latch reaches the new worker
    assert estop.status_code == 200, estop.text


def test_defect_18_a_killed_worker_is_restarted_and_the_stop_recorded(console: Console) -> None:
    run = start_ok(console, console.book(segments=LONG_SESSION))
    console.wait_moving()
    samples_grow(console, run["id"], 1000)
    daemon = console.daemon_pid()
    assert daemon is not None
    processes_before = len(descendants(daemon))
    worker = worker_pids(console)[-1]
    os.kill(worker, signal.SIGKILL)
    ended = wait_run_ended(console, run["id"])
    assert ended["outcome"] == "interrupted", ended
    lost = wait_for(
        lambda: [e for e in console.events(run["id"]) if e["kind"] == "worker_lost"],
        EVENT_TIMEOUT_S,
        "the worker's loss to be recorded on the run",
    )
    details = details_of(lost[0])
    assert details["pid"] == worker and details["signal"] == "SIGKILL", details
    new_worker = wait_for(
        lambda: (pids := worker_pids(console)) and pids[-1] != worker and pids[-1], START_TIMEOUT_S, "a new worker"
    )
    assert alive(new_worker) and console.daemon_pid() == daemon, "the daemon was restarted instead of the worker"
    wait_for(console.robot_ready, START_TIMEOUT_S, "the robot to be ready with its new worker")
    # The dead worker's heartbeat relay went with it: as many processes under the daemon as before.
    wait_for(
        lambda: len(descendants(daemon)) == processes_before,
        EVENT_TIMEOUT_S,
        f"the daemon to have {processes_before} processes again",
    )
    assert_reset_needed_then_free(console, "worker_lost")


def test_defect_18_a_killed_daemon_is_restarted_and_the_stop_recorded(console: Console) -> None:
    run = start_ok(console, console.book(segments=LONG_SESSION))
    console.wait_moving()
    samples_grow(console, run["id"], 1000)
    daemon = console.daemon_pid()
    assert daemon is not None
    os.kill(daemon, signal.SIGKILL)
    ended = wait_run_ended(console, run["id"], timeout_s=START_TIMEOUT_S)  # closed by the next daemon
    assert ended["outcome"] == "interrupted", ended
    lost = [e for e in console.events(run["id"]) if e["kind"] == "daemon_lost"]
    assert lost, f"the daemon's loss was not recorded: {[e['kind'] for e in console.events(run['id'])]}"
    assert details_of(lost[0])["pid"] == daemon, lost
    wait_for(console.robot_ready, START_TIMEOUT_S, "the restarted daemon")
    assert console.daemon_pid() not in (None, daemon)
    assert_reset_needed_then_free(console, "daemon_lost")
