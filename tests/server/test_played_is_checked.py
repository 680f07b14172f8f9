"""The patient feels only what was checked (issue 21, defects 2 and 3): the worker's tick plays the plan's
checked samples and the checked approach, pause and resume, sample for sample, for classical and optimal
cueing; a late tick skips ahead instead of stretching the plan; a plan made for another control rate or
robot description is refused."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from core.plan.build import CheckedPlan, build_plan
from core.plan.check import checked_approach, checked_pause, checked_resume
from core.plan.rejection import PrescriptionRejected
from core.robot import TwinRobot
from server.hal.kinematic import KinematicHal
from server.realtime.pipeline import TickPipeline
from server.realtime.supervisor import Phase, SupervisorConfig, TransitionRefused
from server.realtime.telemetry import StopReason, SupervisorState

RATE_HZ = 250  # every sample is compared: a lower rate keeps the test short, the arithmetic is the same
CONFIG = SupervisorConfig(soft_start_s=0.4, fade_out_s=0.4, pause_hold_s=0.2, pause_stop_s=0.3, return_min_s=0.4)
PRESCRIPTION: dict[str, Any] = {
    "segments": [
        {"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.4, "frequency_hz": 0.5}, "duration_s": 4.0},
        {"cue": {"kind": "step", "axis": "x", "final_m_s2": 0.3, "end_time_s": 1.0}, "duration_s": 2.0},
    ]
}
PATIENT = {"body_mass_kg": 70.0, "height_m": 1.75}


class Session:
    """A pipeline on the ideal HAL, ticked by hand; keeps every stance pose it commanded."""

    def __init__(self, twin: TwinRobot, checked: CheckedPlan, rate_hz: int = RATE_HZ) -> None:
        self.twin, self.plan = twin, checked.plan
        checked.accepted()
        hal = KinematicHal(twin, 1.0 / rate_hz, communication_timeout_s=60.0)
        hal.configure()
        hal.home()
        self.pipeline = TickPipeline(twin, hal, rate_hz, CONFIG, lambda *_: None)
        self.commanded: list[np.ndarray] = []

    def tick(self, lateness_ns: int = 0) -> None:
        self.pipeline.heartbeat()
        self.pipeline.tick(lateness_ns)
        if self.pipeline.wrote_this_tick:
            self.commanded.append(self.pipeline.pose.copy())

    def run_until(self, condition: Any, limit: int = 20_000) -> None:
        for _ in range(limit):
            if condition():
                return
            self.tick()
        raise AssertionError("the session never got there")

    def start(self) -> np.ndarray:
        self.pipeline.load(self.plan)
        self.tick()  # drives off: reads where the platform stands
        approach = checked_approach(self.plan, self.twin, self.pipeline.measured_stance)
        self.pipeline.start(approach)
        return approach.poses


@pytest.fixture(scope="module", params=["classical", "optimal"])
def checked(request: pytest.FixtureRequest, twin: TwinRobot) -> CheckedPlan:
    prescription = {**PRESCRIPTION, "cueing": request.param}
    return build_plan(prescription, twin, control_rate_hz=RATE_HZ, config=CONFIG, patient=PATIENT)


def test_the_played_motion_is_the_checked_one_sample_for_sample_through_a_pause_and_a_resume(
    twin: TwinRobot, checked: CheckedPlan
) -> None:
    session = Session(twin, checked)
    plan, pipeline = checked.plan, session.pipeline
    motion = plan.played
    approach = session.start()
    session.run_until(lambda: pipeline.source.plan_index >= 300)  # well into the first segment's sine
    pause = checked_pause(plan, twin, pipeline.source.plan_index + 20)
    pipeline.pause(pause)
    session.run_until(lambda: pipeline.supervisor.phase is Phase.PARKED)
    parked_ticks = 25
    for _ in range(parked_ticks):
        session.tick()
    resume = checked_resume(plan, twin, pause.after_index + 1)
    pipeline.resume(resume)
    session.run_until(lambda: pipeline.supervisor.state is SupervisorState.STOPPED)
    assert pipeline.supervisor.stop_reason is StopReason.COMPLETED

    assert resume.resume_index is not None
    expected = np.concatenate(
        [
            approach[1:],
            motion.poses[: pause.after_index + 1],
            pause.poses[1:],
            np.repeat(pause.poses[-1:], parked_ticks, axis=0),
            resume.poses[1:],
            motion.poses[resume.resume_index :],
        ]
    )
    played = np.array(session.commanded)
    assert played.shape == expected.shape
    np.testing.assert_array_equal(played, expected)  # bit for bit: nothing in the tick recomputes motion


def test_a_late_tick_skips_ahead_and_never_stretches_the_plan(twin: TwinRobot, checked: CheckedPlan) -> None:
    session = Session(twin, checked)
    pipeline, motion = session.pipeline, checked.plan.played
    session.start()
    session.run_until(lambda: pipeline.source.plan_index >= 100)
    before = pipeline.source.plan_index
    period_ns = round(1e9 / RATE_HZ)
    session.tick(lateness_ns=3 * period_ns + period_ns // 2)  # three periods missed
    assert pipeline.source.plan_index == before + 4
    np.testing.assert_array_equal(pipeline.pose, motion.poses[before + 4])
    assert pipeline.supervisor.state is SupervisorState.RUNNING  # the per-tick limits saw 4 periods pass


def test_a_plan_for_another_control_rate_or_robot_description_is_refused(twin: TwinRobot, checked: CheckedPlan) -> None:
    session = Session(twin, checked, rate_hz=2 * RATE_HZ)
    with pytest.raises(TransitionRefused, match=f"made for {RATE_HZ} Hz; this worker runs at {2 * RATE_HZ} Hz"):
        session.pipeline.load(checked.plan)
    session = Session(twin, checked)
    other = replace(checked.plan, robot_digest="0123456789abcdef")
    with pytest.raises(TransitionRefused, match="made for robot description 0123456789abcdef; this robot's is"):
        session.pipeline.load(other)
    assert session.pipeline.supervisor.state is SupervisorState.IDLE


def test_a_start_is_refused_when_the_platform_moved_since_its_approach_was_checked(
    twin: TwinRobot, checked: CheckedPlan
) -> None:
    session = Session(twin, checked)
    session.pipeline.load(checked.plan)
    session.tick()
    moved = session.pipeline.measured_stance + np.array([0.0, 0.005, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(TransitionRefused, match="from the pose its approach was checked from"):
        session.pipeline.start(checked_approach(checked.plan, twin, moved))
    assert session.pipeline.supervisor.state is SupervisorState.READY and not session.commanded


def test_a_pause_checked_for_a_sample_already_played_is_refused(twin: TwinRobot, checked: CheckedPlan) -> None:
    session = Session(twin, checked)
    pipeline = session.pipeline
    session.start()
    session.run_until(lambda: pipeline.source.plan_index >= 200)
    stale = checked_pause(checked.plan, twin, pipeline.source.plan_index - 10)
    with pytest.raises(TransitionRefused, match="is played already"):
        pipeline.pause(stale)
    assert pipeline.supervisor.state is SupervisorState.RUNNING


def test_a_transition_that_would_break_a_limit_is_refused_naming_it(twin: TwinRobot) -> None:
    tight = {**PRESCRIPTION["segments"][0], "limits": {"slider_velocity_max_m_s": 0.02}}
    checked = build_plan(
        {"segments": [{**tight, "cue": {**tight["cue"], "amplitude_m_s2": 0.05}}]},
        twin,
        control_rate_hz=RATE_HZ,
        config=CONFIG,
    )
    plan = checked.plan
    checked.accepted()
    far = np.array([0.0, 0.08, 0.0, 0.0, 0.0, 0.0])  # standing 80 mm aside: the quick approach is too fast
    with pytest.raises(PrescriptionRejected, match=r"\(approach, .*slider velocity"):
        checked_approach(plan, twin, far)


def test_a_stop_never_waits_for_a_pause_being_checked(
    robot_client: Any, seed: Any, fake_worker: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The daemon builds and checks a pause outside its lock: a stop asked for meanwhile answers at once."""
    import threading

    from benchmarks.fault_harness import in_background
    from server.robotd import playback
    from tests.server.conftest import booked_session

    checking, release, finished = threading.Event(), threading.Event(), threading.Event()
    real_check = playback.checked_pause

    def slow_check(*arguments: Any) -> Any:
        checking.set()
        release.wait(20.0)  # a long check; the stop must not wait for it
        finished.set()
        return real_check(*arguments)

    monkeypatch.setattr(playback, "checked_pause", slow_check)
    booked = booked_session(robot_client, seed.headers())
    base = f"/api/v1/sessions/{booked.session_id}"
    assert robot_client.post(f"{base}/start", headers=seed.headers()).status_code == 200
    pauser, paused = in_background(lambda: robot_client.post(f"{base}/pause", headers=seed.headers()))
    assert checking.wait(60.0)
    try:
        stopped = robot_client.post(f"{base}/stop", headers=seed.headers())  # while the pause is being checked
        assert not finished.is_set(), "the stop waited for the pause's check"
        assert stopped.status_code == 200 and stopped.json()["outcome"] == "stopped"
        assert "stop" in fake_worker.command_names() and "pause" not in fake_worker.command_names()
    finally:
        release.set()
    pauser.join(60.0)
    assert not pauser.is_alive() and paused[0].status_code == 409  # the run it would have paused had ended
