"""Issue 20, defect 2: an emergency stop or a stop cancels a start that is still loading; a reset never lets
it begin. In the daemon (a fake worker whose load waits for the test), in the real worker (the start
carries the emergency-stop count it was requested under), and end to end with real processes."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from server.messages import CommandRefused
from server.realtime.client import WorkerClient
from server.robotd.playback import plan_and_load
from tests.server.conftest import FakeWorker, Seed, booked_session, wait_until


def _start_in_background(client: TestClient, seed: Seed, session_id: int) -> tuple[threading.Thread, list[Any]]:
    answers: list[Any] = []
    thread = threading.Thread(
        target=lambda: answers.append(client.post(f"/api/v1/sessions/{session_id}/start", headers=seed.headers())),
        daemon=True,
    )
    thread.start()
    return thread, answers


@pytest.fixture
def slow_load(fake_worker: FakeWorker) -> Iterator[threading.Event]:
    """The fake worker's load waits until the test sets this (a long offline check)."""
    gate = threading.Event()
    fake_worker.load_gate = gate
    try:
        yield gate
    finally:
        gate.set()


def test_an_emergency_stop_cancels_a_loading_start_and_a_reset_never_lets_it_begin(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker, slow_load: threading.Event
) -> None:
    booked = booked_session(robot_client, seed.headers())
    starter, answers = _start_in_background(robot_client, seed, booked.session_id)
    assert fake_worker.loading.wait(30.0), "the start never reached the load"
    estop = robot_client.post("/api/v1/estop")
    assert estop.status_code == 200, estop.text
    reset = robot_client.post("/api/v1/robot/reset", headers=seed.headers())
    assert reset.status_code == 200, reset.text
    slow_load.set()  # the load finishes after the reset
    starter.join(60.0)
    assert answers, "the start never answered"
    start = answers[0]
    assert start.status_code == 409, f"the start went on after the emergency stop and the reset: {start.text}"
    assert "start cancelled by the emergency stop at" in start.json()["detail"], start.text
    assert "start_motion" not in fake_worker.command_names(), fake_worker.command_names()
    runs = robot_client.get(f"/api/v1/sessions/{booked.session_id}/runs", headers=seed.headers()).json()
    assert runs == [], f"a run was recorded for a cancelled start: {runs}"
    assert robot_client.app.state.robot.active_run() is None


def test_a_stop_cancels_a_loading_start(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker, slow_load: threading.Event
) -> None:
    booked = booked_session(robot_client, seed.headers())
    starter, answers = _start_in_background(robot_client, seed, booked.session_id)
    assert fake_worker.loading.wait(30.0), "the start never reached the load"
    stop = robot_client.post(f"/api/v1/sessions/{booked.session_id}/stop", headers=seed.headers())
    assert stop.status_code == 200, f"the stop did not cancel the loading start: {stop.text}"
    assert stop.json()["status"] == "start cancelled" and stop.json()["scheduled_session_id"] == booked.session_id
    slow_load.set()
    starter.join(60.0)
    assert answers and answers[0].status_code == 409, answers and answers[0].text
    assert "start cancelled by the stop at" in answers[0].json()["detail"], answers[0].text
    assert "start_motion" not in fake_worker.command_names(), fake_worker.command_names()
    assert robot_client.get(f"/api/v1/sessions/{booked.session_id}/runs", headers=seed.headers()).json() == []
    # The robot is free: the next start goes through.
    fake_worker.load_gate = None
    again = robot_client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers())
    assert again.status_code == 200, again.text


def test_a_stop_of_another_session_leaves_a_loading_start_alone(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker, slow_load: threading.Event
) -> None:
    booked = booked_session(robot_client, seed.headers())
    other = booked_session(robot_client, seed.headers(), identifier="MRN-2", start="2031-05-06T11:00:00+00:00")
    starter, answers = _start_in_background(robot_client, seed, booked.session_id)
    assert fake_worker.loading.wait(30.0)
    stop = robot_client.post(f"/api/v1/sessions/{other.session_id}/stop", headers=seed.headers())
    assert stop.status_code == 409 and "no active run" in stop.json()["detail"], stop.text
    slow_load.set()
    starter.join(60.0)
    assert answers and answers[0].status_code == 200, answers and answers[0].text


# --- the real worker: defence in depth ------------------------------------------------------------------

SHORT = {"segments": [{"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.3, "frequency_hz": 0.5},
                       "duration_s": 4.0}]}  # fmt: skip


@pytest.mark.slow
def test_the_worker_refuses_a_load_or_start_requested_before_an_emergency_stop() -> None:
    with WorkerClient(None, "kinematic", hal_options={"communication_timeout_s": 1.0}) as client:
        generation, _ = client.estop_request()
        client.emergency_stop()
        wait_until(lambda: client.latest_state()["estop_latched"], 30.0)
        client.reset()
        wait_until(lambda: not client.latest_state()["estop_latched"], 30.0)
        with pytest.raises(CommandRefused, match="emergency stop was requested after"):
            plan_and_load(client, SHORT, estop_generation=generation)
        current, utc_s = client.estop_request()
        assert current == generation + 1 and utc_s is not None and abs(utc_s - time.time()) < 60.0
        plan_and_load(client, SHORT, estop_generation=current)  # a start asked for after the stop loads
        client.emergency_stop()
        wait_until(lambda: client.latest_state()["estop_latched"], 30.0)
        client.reset()
        wait_until(lambda: client.latest_state()["state"] in ("idle", "ready", "stopped"), 30.0)
        playback, _ = plan_and_load(client, SHORT, estop_generation=current + 1)
        with pytest.raises(CommandRefused, match="emergency stop was requested after"):
            playback.start(client, estop_generation=current)
        assert client.latest_state()["state"] != "running"


# --- end to end: `serve`, its daemon, its planning process and worker as real processes --------------------


@pytest.mark.slow
def test_an_emergency_stop_cancels_a_loading_start_in_every_trial(tmp_path: Path) -> None:
    from benchmarks.fault_harness import Console
    from benchmarks.start_cancel import cancel_loading_start

    console = Console(tmp_path / "console")
    console.start()
    try:
        for trial in range(3):
            outcome = cancel_loading_start(console)
            assert outcome.cancelled, f"trial {trial + 1}: the start was not cancelled: {outcome}"
            assert not outcome.moved, f"trial {trial + 1}: the robot moved after the emergency stop: {outcome}"
            assert outcome.runs_recorded == 0, f"trial {trial + 1}: a run was recorded: {outcome}"
    finally:
        console.stop()
