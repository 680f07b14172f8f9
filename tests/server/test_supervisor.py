"""The safety supervisor and the per-tick pipeline, run tick by tick in-process on the kinematic HAL."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from core.kinematics import twin_inverse_kinematics
from core.plan.build import PrescriptionPlan, plan_prescription
from core.plan.check import checked_approach, checked_pause, checked_resume
from core.plan.motion import approach
from core.plan.ramps import PoseRamp
from core.robot import TwinRobot
from core.twin_kernels import TwinKernels
from server.hal.base import DriveState, HalState, HardwareInterface
from server.hal.kinematic import KinematicHal
from server.realtime.pipeline import TickPipeline
from server.realtime.supervisor import Phase, Supervisor, SupervisorConfig, SupervisorConfigError, TransitionRefused
from server.realtime.telemetry import StopReason, SupervisorState

S = SupervisorState
RATE_HZ = 1000
FAST = SupervisorConfig(soft_start_s=0.2, fade_out_s=0.2, pause_hold_s=0.1, return_min_s=0.2, controlled_stop_s=0.2)
SINE = {"kind": "sine", "axis": "y", "amplitude_m_s2": 1.5, "frequency_hz": 1.0}


class Harness:
    """A pipeline on an ideal HAL, ticked as fast as Python goes; records every command sent."""

    def __init__(
        self, twin: TwinRobot, config: SupervisorConfig = FAST, hal: HardwareInterface | None = None, **hal_options: Any
    ) -> None:
        hal_options.setdefault("communication_timeout_s", 30.0)  # ticks here are not paced in real time
        self.hal: Any = hal or KinematicHal(twin, 1.0 / RATE_HZ, **hal_options)
        self.hal.configure()
        self.hal.home()
        self.events: list[tuple[str, dict[str, Any], str | None]] = []
        self.pipeline = TickPipeline(twin, self.hal, RATE_HZ, config, lambda k, d, det: self.events.append((k, d, det)))
        self.twin = twin
        self.poses: list[np.ndarray] = []
        self.sliders: list[np.ndarray] = []
        self.plan: PrescriptionPlan | None = None

    @property
    def state(self) -> SupervisorState:
        return self.pipeline.supervisor.state

    def load(self, cue: dict[str, Any] = SINE, duration_s: float = 2.0, limits: dict[str, float] | None = None) -> None:
        segment: dict[str, Any] = {"cue": cue, "duration_s": duration_s}
        if limits:
            segment["limits"] = limits
        self.plan = plan_prescription({"segments": [segment]}, self.twin, config=self.pipeline.config)
        self.pipeline.load(self.plan)
        self.paused_after = -1

    def start(self) -> None:
        """Start along the checked approach from where the platform stands (unchecked without a plan: the
        pipeline refuses the start before it looks at the approach)."""
        self.run(1, heartbeat=False)  # the drives are off: reads the platform's pose
        standing = self.pipeline.measured_stance
        if self.plan is None:
            self.pipeline.start(approach(standing, 1.0 / RATE_HZ, self.pipeline.config))
        else:
            self.pipeline.start(checked_approach(self.plan, self.twin, standing))

    def pause(self) -> None:
        """Arm the checked pause, 10 samples ahead of the one played."""
        assert self.plan is not None
        self.paused_after = self.pipeline.source.plan_index + 10
        self.pipeline.pause(checked_pause(self.plan, self.twin, self.paused_after))

    def resume(self) -> None:
        assert self.plan is not None
        self.pipeline.resume(checked_resume(self.plan, self.twin, self.paused_after + 1))

    def run(
        self, ticks: int, *, heartbeat: bool = True, lateness_ns: int = 0, until: Callable[[], bool] | None = None
    ) -> int:
        for count in range(ticks):
            if heartbeat:
                self.pipeline.heartbeat()
            self.pipeline.tick(lateness_ns)
            if self.pipeline.wrote_this_tick:
                self.poses.append(self.pipeline.pose.copy())
                self.sliders.append(self.pipeline.command.positions_m.copy())
            if until is not None and until():
                return count + 1
        return ticks

    def kinds(self) -> list[str]:
        return [kind for kind, _, _ in self.events]

    def go_to(self, target: SupervisorState) -> None:
        """Drive the session into `target` through the normal commands."""
        p = self.pipeline
        if target is S.IDLE:
            return
        if target is S.FAULT:
            self.hal.fault("test: drive fault")
            self.run(1)
            return
        if target is S.ESTOP:
            p.emergency_stop()
            self.run(400)
            return
        self.load()
        if target is S.READY:
            return
        self.start()
        self.run(600)  # approach, then into the cue
        if target is S.RUNNING:
            return
        if target is S.PAUSED:
            self.pause()
            self.run(50)
            return
        p.stop()
        self.run(10)
        if target is S.STOPPING:
            return
        self.run(20_000, until=lambda: self.state is S.STOPPED)


@pytest.fixture
def harness(twin: TwinRobot) -> Harness:
    return Harness(twin)


def test_normal_session_walks_through_every_state(harness: Harness) -> None:
    p = harness.pipeline
    assert harness.state is S.IDLE
    harness.load()
    assert harness.state is S.READY and harness.hal.state is HalState.CONFIGURED
    harness.start()
    harness.run(300)
    assert harness.state is S.RUNNING and harness.hal.state is HalState.ACTIVE
    assert p.supervisor.phase is Phase.CUE
    harness.pause()
    ticks = harness.run(5000, until=lambda: p.supervisor.phase is Phase.PARKED)
    assert harness.state is S.PAUSED and ticks < 5000
    np.testing.assert_allclose(p.pose, 0.0, atol=1e-9)  # pause washes out to neutral
    harness.resume()
    harness.run(300)
    assert harness.state is S.RUNNING
    p.stop()
    harness.run(10)
    assert harness.state is S.STOPPING
    harness.run(20_000, until=lambda: harness.state is S.STOPPED)
    assert harness.state is S.STOPPED and harness.hal.state is HalState.CONFIGURED
    np.testing.assert_allclose(harness.sliders[-1], p.neutral_sliders, atol=1e-9)
    visited = [d["to"] for k, d, _ in harness.events if k == "state"]
    assert visited == ["ready", "running", "paused", "running", "stopping", "stopped"]


def test_a_prescription_plays_to_its_end_and_returns_to_neutral(harness: Harness) -> None:
    harness.load(duration_s=1.0)
    harness.start()
    harness.run(30_000, until=lambda: harness.state is S.STOPPED)
    assert harness.state is S.STOPPED
    assert harness.pipeline.supervisor.stop_reason is StopReason.COMPLETED
    assert "prescription_completed" in harness.kinds()
    np.testing.assert_allclose(harness.poses[-1], 0.0, atol=1e-9)


def test_commands_in_the_wrong_state_are_refused(harness: Harness) -> None:
    p = harness.pipeline
    standing = approach(np.zeros(6), 1.0 / RATE_HZ, p.config)
    for command in (harness.start, lambda: p.pause(standing), lambda: p.resume(standing), p.stop, p.reset):
        with pytest.raises(TransitionRefused):
            command()
    harness.load()
    with pytest.raises(TransitionRefused, match="resume"):
        harness.resume()
    harness.start()
    harness.run(300)
    with pytest.raises(TransitionRefused, match="load"):
        harness.load()
    harness.pause()
    harness.run(5)
    with pytest.raises(TransitionRefused, match="returning to neutral"):
        harness.resume()  # only once parked at neutral


@pytest.mark.parametrize("origin", list(SupervisorState), ids=[s.label for s in SupervisorState])
def test_emergency_stop_from_every_state_latches_and_reset_never_restarts_motion(
    twin: TwinRobot, origin: SupervisorState
) -> None:
    harness = Harness(twin)
    harness.go_to(origin)
    assert harness.state is origin
    harness.pipeline.emergency_stop()
    harness.run(400)  # longer than the 0.3 s ramp
    assert harness.state is S.ESTOP
    assert harness.pipeline.supervisor.estop_latched
    assert harness.hal.state is HalState.ESTOP
    assert set(harness.hal.drive_states) == {DriveState.SWITCH_ON_DISABLED}
    positions = harness.hal._positions.copy()
    with pytest.raises(TransitionRefused):
        harness.start()  # latched: nothing starts until an explicit reset
    harness.pipeline.reset()
    writes = harness.hal.writes
    harness.run(500)
    assert harness.state is S.IDLE and not harness.pipeline.supervisor.estop_latched
    assert harness.hal.state is HalState.CONFIGURED  # drives stay off after the reset
    assert harness.hal.writes == writes
    np.testing.assert_array_equal(harness.hal._positions, positions)


def test_estop_while_running_reaches_standstill_within_the_ramp_with_bounded_jerk(harness: Harness) -> None:
    p, period = harness.pipeline, 1.0 / RATE_HZ
    harness.load(duration_s=5.0)
    harness.start()
    harness.run(1200)
    speed_before = np.abs(np.diff(harness.sliders[-2:], axis=0)).max() / period
    assert speed_before > 0.01  # it really was moving
    moving_poses = len(harness.poses)
    p.emergency_stop()
    ramp_ticks = round(p.config.estop_ramp_s * RATE_HZ)
    harness.run(ramp_ticks + 5)
    stop_poses = np.array(harness.poses[moving_poses - 3 :])
    assert len(stop_poses) - 3 <= ramp_ticks  # no set-point after the ramp: the drives were disabled
    final_step = np.abs(np.diff(harness.sliders[-2:], axis=0)).max() / period
    assert final_step < 1e-3 * speed_before  # standstill at the end of the ramp
    assert harness.hal.state is HalState.ESTOP
    jerk = np.abs(np.diff(stop_poses, n=3, axis=0)).max() / period**3
    ramp = PoseRamp()
    acceleration = (stop_poses[2] - 2 * stop_poses[1] + stop_poses[0]) / period**2
    velocity = (stop_poses[2] - stop_poses[1]) / period + 0.5 * period * acceleration
    ramp.to_standstill(stop_poses[2], velocity, acceleration, p.config.estop_ramp_s)
    assert jerk < 1.5 * ramp.peak_jerk().max() + 1.0  # bounded by the ramp's own jerk: no step at the switch
    latency = [d for k, d, _ in harness.events if k == "estop_reached_hal"]
    assert latency and latency[0]["action"] == "first stop set-point"


@pytest.mark.slow
def test_estop_while_running_in_the_sim_comes_to_a_standstill_within_the_ramp(twin: TwinRobot) -> None:
    from server.hal.sim.backend import SimHal

    harness = Harness(twin, hal=SimHal(twin, 1.0 / RATE_HZ))
    harness.load(duration_s=5.0)
    harness.start()
    harness.run(1500)
    assert harness.state is S.RUNNING
    assert np.abs(harness.pipeline.reading.velocities_m_s).max() > 0.01  # the physics really moves
    harness.pipeline.emergency_stop()
    ramp_ticks = round(harness.pipeline.config.estop_ramp_s * RATE_HZ)
    harness.run(ramp_ticks - 2)
    assert harness.hal.state is HalState.ACTIVE  # still ramping down under control
    harness.run(3)
    assert harness.hal.state is HalState.ESTOP and harness.state is S.ESTOP
    assert np.abs(harness.pipeline.reading.velocities_m_s).max() < 0.005  # standstill at the ramp's end
    assert set(harness.pipeline.reading.drive_states) <= {DriveState.SWITCH_ON_DISABLED, DriveState.QUICK_STOP_ACTIVE}


def test_watchdog_stops_motion_after_100_ms_without_heartbeat(harness: Harness) -> None:
    harness.load(duration_s=5.0)
    harness.start()
    harness.run(800)
    harness.run(99, heartbeat=False)
    assert harness.state is S.RUNNING
    harness.run(3, heartbeat=False)
    assert harness.state is S.STOPPING
    assert harness.pipeline.supervisor.stop_reason is StopReason.WATCHDOG
    harness.run(20_000, heartbeat=False, until=lambda: harness.state is S.STOPPED)
    assert harness.state is S.STOPPED and harness.hal.state is HalState.CONFIGURED
    np.testing.assert_allclose(harness.poses[-1], 0.0, atol=1e-9)


def test_start_is_refused_without_a_live_heartbeat(harness: Harness) -> None:
    harness.load()
    harness.run(150, heartbeat=False)
    with pytest.raises(TransitionRefused, match="heartbeat"):
        harness.start()


def test_consecutive_late_ticks_trigger_a_controlled_stop(harness: Harness) -> None:
    late_limit = harness.pipeline.config.late_ticks_to_stop
    harness.load(duration_s=5.0)
    harness.start()
    harness.run(500)
    harness.run(late_limit - 1, lateness_ns=800_000)
    harness.run(1)  # an on-time tick resets the streak
    harness.run(late_limit - 1, lateness_ns=800_000)
    assert harness.state is S.RUNNING
    harness.run(1, lateness_ns=800_000)
    assert harness.state is S.STOPPING
    assert harness.pipeline.supervisor.stop_reason is StopReason.LATE_TICKS
    assert harness.pipeline.deadline_misses == 2 * late_limit - 1


def test_a_limit_hit_is_a_controlled_stop_with_an_event_and_no_command_breaks_the_limit(
    harness: Harness, twin: TwinRobot
) -> None:
    tilt_max = 0.05
    step = {"kind": "step", "axis": "y", "final_m_s2": 1.96, "step_time_s": 0.3}  # tilts to 0.2 rad if allowed
    harness.load(step, duration_s=8.0, limits={"tilt_max_rad": tilt_max})  # loaded unchecked, on purpose
    harness.start()
    harness.run(20_000, until=lambda: harness.state is S.STOPPED)
    assert harness.state is S.STOPPED
    assert harness.pipeline.supervisor.stop_reason is StopReason.LIMIT
    hits = [d for k, d, _ in harness.events if k == "limit_hit"]
    margin = harness.pipeline.config.limit_margin_fraction
    assert hits and hits[0]["limit"] == "tilt" and hits[0]["limit_value"] == pytest.approx(tilt_max * (1 - margin))
    poses = np.array(harness.poses)
    tilt = np.arccos(np.cos(poses[:, 3]) * np.cos(poses[:, 4]))
    braking_from = int(np.argmax(tilt > tilt_max * (1 - margin)))
    assert braking_from > 0  # every cue set-point stayed inside the margined limit ...
    assert tilt.max() <= twin.robot.limits.tilt_max_rad  # ... and braking stayed inside the robot's own limit
    assert harness.pipeline.record["limit_hits"][0] >= 1


def test_a_hal_fault_faults_the_supervisor(harness: Harness) -> None:
    harness.load()
    harness.start()
    harness.run(300)
    harness.hal.fault("drive 3: following error")
    harness.run(1)
    assert harness.state is S.FAULT
    assert harness.pipeline.supervisor.stop_reason is StopReason.HAL_FAULT
    harness.pipeline.reset()
    assert harness.state is S.IDLE and harness.hal.state is HalState.CONFIGURED


def test_the_kinematic_drives_stop_by_themselves_when_set_points_stop(twin: TwinRobot) -> None:
    harness = Harness(twin, communication_timeout_s=0.02)
    harness.load()
    harness.start()
    harness.run(5)
    time.sleep(0.03)
    harness.run(1)
    assert harness.hal.state is HalState.FAULT and "communication lost" in (harness.hal.last_fault or "")
    assert harness.state is S.FAULT


def test_per_tick_kinematics_match_the_batch_reference(twin: TwinRobot) -> None:
    kernels = TwinKernels(twin, 1.0 / RATE_HZ)
    rng = np.random.default_rng(5)
    poses = rng.uniform(-1, 1, (50, 6)) * np.array([0.08, 0.08, 0.04, 0.08, 0.08, 0.08])
    reference = twin_inverse_kinematics(twin, poses, check=False)
    sliders, velocity, acceleration, violation = np.zeros(12), np.zeros(12), np.zeros(12), np.zeros(4)
    for index, pose in enumerate(poses):
        kernels.command(
            pose,
            sliders.copy(),
            velocity.copy(),
            np.full(12, -9.0),
            np.full(12, 9.0),
            np.array([9.0] * 6 + [0.0]),  # the kernel's limits vector (core.plan.limits.SessionLimits.kernel_vector)
            sliders,
            velocity,
            acceleration,
            violation,
        )
        expected = np.concatenate(
            [reference["right"].slider_positions_m[index], reference["left"].slider_positions_m[index]]
        )
        np.testing.assert_allclose(sliders, expected, atol=1e-12)
        stance = np.zeros(6)
        kernels.measured_stance_pose(sliders[:6], stance)
        np.testing.assert_allclose(stance, pose, atol=1e-9)


def test_pure_state_machine_refuses_and_reports() -> None:
    events: list[str] = []
    supervisor = Supervisor(SupervisorConfig(), lambda kind, details: events.append(kind))
    supervisor.load()
    supervisor.start()
    supervisor.controlled_stop(StopReason.FALL, {"detector": "harness_load"})
    assert supervisor.state is S.STOPPING and supervisor.stop_reason is StopReason.FALL
    supervisor.controlled_stop(StopReason.WATCHDOG, {})  # already stopping: the first reason stays
    assert supervisor.stop_reason is StopReason.FALL
    with pytest.raises(TransitionRefused):
        supervisor.reset()  # not while the stop ramp runs
    assert "controlled_stop" in events
    with pytest.raises(SupervisorConfigError) as refused:
        SupervisorConfig(estop_ramp_s=-1.0)
    assert refused.value.field == "estop_ramp_s"
