"""One control tick of the twin, played in the phases the supervisor decides.

    checked motion (the plan's sample for this time, or a checked transition's) → IK of both robots →
    limits (stroke, rod reach, joint cones, tilt, slider velocity and acceleration, predicted drive force
    from the inverse dynamics) → HAL write → HAL read → FK monitoring (tracking error) → fall detectors →
    telemetry

The motion the patient feels is only ever what was checked (`core.plan.motion`): the plan's samples,
indexed by time (a late tick skips ahead; it never stretches the plan), and the approach, pause and
resume transitions, each checked before it was sent here. The tick computes motion of its own only for
the safety reactions: the bounded-jerk ramps (`ramps`) of controlled and emergency stops and the return
to neutral after a stop, checked here tick by tick against the robot's own limits.

A limit hit does not raise: the command is not sent, the supervisor starts a controlled stop from the last
command sent, and that stop's first set-point goes out in the same tick. If even a stop ramp would break a
limit the drives quick-stop (FAULT; ESTOP if it was the emergency stop's ramp). Every exception inside a
tick is caught and turned into a fault with an event; the loop itself never dies.
"""

from __future__ import annotations

import time
import traceback
from collections.abc import Callable
from typing import Any

import numpy as np

from core.dynamics import TwinInverseDynamics
from core.falls import FallMonitor
from core.kinematics import ForwardKinematicsError
from core.plan.build import PrescriptionPlan
from core.plan.limits import LIMIT_UNITS, LimitCode, SessionLimits
from core.plan.motion import Transition
from core.plan.ramps import PoseRamp, start_velocity
from core.robot import TwinRobot, twin_digest
from core.twin_kernels import VIOLATION_FIELDS, TwinKernels
from server.hal.base import (
    AXIS_COUNT,
    CommandRejectedError,
    HalCommand,
    HalError,
    HalReading,
    HalState,
    HardwareInterface,
)
from server.realtime.loop import LATE_THRESHOLD_NS
from server.realtime.motion_source import PlayedPlan
from server.realtime.supervisor import Phase, Supervisor, SupervisorConfig, TransitionRefused
from server.realtime.telemetry import HAL_STATE_CODES, TELEMETRY_DTYPE, StopReason, SupervisorState

EventEmitter = Callable[[str, dict[str, Any], "str | None"], None]
# The platform may stand this far (m, rad per axis) from the pose its approach was checked from: drives
# that hold still read back within microns; more means it moved (or was moved) since the check.
APPROACH_START_TOLERANCE = 1e-3


class TickPipeline:
    """The worker's tick: owns the supervisor, the motion state, the limits and the telemetry record; the
    checked motion comes from its motion source (`server.realtime.motion_source`)."""

    def __init__(
        self,
        twin: TwinRobot,
        hal: HardwareInterface,
        control_rate_hz: int,
        config: SupervisorConfig,
        emit: EventEmitter,
    ) -> None:
        self.twin, self.hal, self.config = twin, hal, config
        self.control_rate_hz = control_rate_hz
        self.period_s = 1.0 / control_rate_hz
        self._emit_to_worker = emit
        self.supervisor = Supervisor(config, self._supervisor_event)
        self.kernels = TwinKernels(twin, self.period_s)
        self.neutral_sliders = self.kernels.neutral_sliders()
        self.default_limits = SessionLimits.for_twin(twin)  # the robot's own: what braking is held to
        self.robot_digest = twin_digest(twin)
        self.source: PlayedPlan | None = None  # the checked motion loaded (None: none)
        self.dynamics = TwinInverseDynamics(twin)
        self.fall_monitor: FallMonitor | None = None
        # The patient's detectors this backend cannot run (it reads no plates); None: all run as configured.
        self.detectors_off: list[str] | None = None
        # Motion state: the last stance command sent and its finite-difference derivatives.
        # The telemetry record is the working memory: HAL readings, commands and poses are views into
        # it, so publishing a tick copies no arrays.
        self.record = np.zeros(1, TELEMETRY_DTYPE)
        view = self._record_view
        self.pose = view("stance_pose")
        self.velocity = np.zeros(6)
        self.acceleration = np.zeros(6)
        self._candidate = np.zeros(6)
        self._candidate_velocity = np.zeros(6)
        self._candidate_acceleration = np.zeros(6)
        self.previous_sliders = self.neutral_sliders.copy()
        self.previous_slider_velocity = np.zeros(AXIS_COUNT)
        self._sliders = np.zeros(AXIS_COUNT)
        self._slider_velocity = np.zeros(AXIS_COUNT)
        self._slider_acceleration = np.zeros(AXIS_COUNT)
        self._violation = np.zeros(VIOLATION_FIELDS)
        self._tracking = np.zeros(AXIS_COUNT)
        self._zero3 = np.zeros(3)
        self._predicted_force = np.zeros(AXIS_COUNT)
        self._cue_force, self._cue_angular = view("cue_specific_force_m_s2"), view("cue_angular_velocity_rad_s")
        self.ramp = PoseRamp()
        self._ramp_start_velocity = np.zeros(6)
        self.command = HalCommand(
            positions_m=view("slider_command_m"),
            velocity_feedforward_m_s=np.zeros(AXIS_COUNT),
            force_feedforward_n=view("predicted_force_n"),
        )
        self.reading = HalReading(
            positions_m=view("slider_position_m"),
            velocities_m_s=view("slider_velocity_m_s"),
            drive_forces_n=view("drive_force_n"),
            drive_states=view("drive_state"),
            plate_force_z_n=view("plate_force_z_n"),
            plate_cop_m=view("plate_cop_m"),
        )
        self.measured_stance = view("measured_stance_pose")
        self.phase_time_s = 0.0
        self.step_s = self.period_s  # time since the previous set-point: a period, or more after a late tick
        self.tick_index = -1
        self.start_ns = time.perf_counter_ns()
        self.period_ns = round(1e9 / control_rate_hz)
        # One clock for a session: each tick is stamped once, at its start, with perf_counter; telemetry, the
        # fall detectors and every event's `session_time_s` are read from that stamp (ticks × period drifts
        # from it whenever the loop skips a deadline).
        self.tick_ns = self.start_ns
        self.tick_time_s = 0.0  # since the worker started
        self.session_start_ns: int | None = None
        self.session_time_s = 0.0  # since the session's start
        self.skipped_ticks = 0
        self.deadline_misses = 0
        self.limit_hits = 0
        self.last_limit = LimitCode.NONE
        self.tracking_error_m = 0.0
        self.fk_iterations = 0
        self.wrote_this_tick = False
        self._estop_request_ns: int | None = None
        self.estop_latency_ms: float | None = None
        # A property of the robot, constant: the console shows it as "fall detection off".
        self.record["fall_detection_unavailable"] = not hal.measures_patient_loads
        self._limits_vector = self.default_limits.kernel_vector()
        self._stroke_min, self._stroke_max = self.default_limits.stroke_min_m, self.default_limits.stroke_max_m

    # --- commands (from the worker's command channel) ---------------------------------------------

    def load(self, plan: PrescriptionPlan) -> None:
        """Take a checked plan (drives off). One made for another control rate or robot description is
        refused: its samples would be played at the wrong times, or on a robot nobody checked them for."""
        self.supervisor.require("load", SupervisorState.IDLE, SupervisorState.READY, SupervisorState.STOPPED)
        state = self.supervisor.state
        if plan.control_rate_hz != self.control_rate_hz:
            raise TransitionRefused(
                "load",
                state,
                f"the plan was made for {plan.control_rate_hz} Hz; this worker runs at {self.control_rate_hz} Hz",
            )
        if plan.robot_digest != self.robot_digest:
            raise TransitionRefused(
                "load",
                state,
                f"the plan was made for robot description {plan.robot_digest or '(none)'}; this robot's is "
                f"{self.robot_digest}",
            )
        # The drives carry the patient whatever the backend reads: the payload is in the drive forces.
        payload = plan.patient.payload() if plan.patient else None
        self.dynamics = TwinInverseDynamics(self.twin, payload)
        monitor = FallMonitor(plan.patient.fall_detectors, self.period_s) if plan.patient else None
        # Every detector reads the force plates or the harness load cell. A backend that reads neither leaves
        # them at zero, an empty platform: the detectors would end every session as a fall at once. None runs
        # there (the drive forces carry the patient's weight, but no detector is validated on them).
        if monitor is not None and not self.hal.measures_patient_loads:
            self.fall_monitor, self.detectors_off = None, [detector.name for detector in monitor.detectors]
        else:
            self.fall_monitor, self.detectors_off = monitor, None
        if self.hal.simulates_patient:
            self.hal.attach_patient(plan.patient)
        self.source = PlayedPlan(plan, self.supervisor, self._use_limits)
        self.supervisor.load()
        self._emit(
            "prescription_loaded",
            {
                "segments": len(plan.segments),
                "samples": self.source.motion.samples,
                "patient": plan.patient is not None,
                "control_rate_hz": self.control_rate_hz,
            },
            None,
        )

    def start(self, approach: Transition) -> None:
        """Start with the checked approach from where the platform stands to neutral, then the plan."""
        self.supervisor.require("start", SupervisorState.READY)
        state = self.supervisor.state
        if self.hal.state is not HalState.CONFIGURED:
            raise TransitionRefused("start", state, f"HAL is {self.hal.state.value}")
        if approach.kind != "approach":
            raise TransitionRefused("start", state, f"a start begins with an approach, not a {approach.kind}")
        offset = float(np.max(np.abs(self.measured_stance - approach.poses[0])))
        if offset > APPROACH_START_TOLERANCE:
            raise TransitionRefused(
                "start",
                state,
                f"the platform stands {offset:.6f} m (or rad) from the pose its approach was checked from "
                f"(limit {APPROACH_START_TOLERANCE:g}): it moved since; start again",
            )
        assert self.source is not None  # READY: a plan is loaded
        self.source.begin(approach)
        if self.fall_monitor is not None:
            self.fall_monitor.reset()
        self.session_start_ns = time.perf_counter_ns()
        self.session_time_s = 0.0
        self.supervisor.start()
        if self.detectors_off is not None:
            backend = type(self.hal).__name__.removesuffix("Hal").lower()
            self._emit(
                "fall_detection_unavailable",
                {
                    "reason": f"the {backend} backend reads no force plates or harness load cell: falls are not "
                    "detected automatically in this run; the harness still catches",
                    "detectors_off": self.detectors_off,
                },
                None,
            )

    def pause(self, transition: Transition) -> None:
        """Arm a checked pause: the plan plays on to its sample `after_index`, then the pause takes over."""
        supervisor = self.supervisor
        supervisor.require("pause", SupervisorState.RUNNING)
        if transition.kind != "pause":
            raise TransitionRefused("pause", supervisor.state, f"a {transition.kind} is no pause")
        source = self.source
        assert source is not None  # RUNNING: a plan is loaded
        if source.transition is not None or supervisor.phase is not Phase.CUE:
            kind = source.transition.kind if source.transition is not None else supervisor.phase.name.lower()
            raise TransitionRefused("pause", supervisor.state, f"not during the {kind}: wait until it is over, or stop")
        if transition.after_index <= source.plan_index:
            raise TransitionRefused(
                "pause",
                supervisor.state,
                f"checked to begin after plan sample {transition.after_index}; sample {source.plan_index} is "
                "played already",
            )
        source.arm_pause(transition)
        supervisor.pause()

    def resume(self, transition: Transition) -> None:
        """Back into the plan along the checked resume, from neutral, where the pause parked."""
        supervisor = self.supervisor
        if transition.kind != "resume":
            raise TransitionRefused("resume", supervisor.state, f"a {transition.kind} is no resume")
        parked = supervisor.state is SupervisorState.PAUSED and supervisor.phase is Phase.PARKED
        if parked and not np.allclose(self.pose, transition.poses[0], atol=1e-9):
            raise TransitionRefused("resume", supervisor.state, "the resume was checked from another pose")
        supervisor.resume()
        assert self.source is not None  # PAUSED: a plan is loaded
        self.source.play_transition(transition)

    def stop(self) -> None:
        self.supervisor.stop()

    def emergency_stop(self, request_ns: int | None = None) -> None:
        if self.supervisor.state is SupervisorState.ESTOP:
            return
        self._estop_request_ns = request_ns if request_ns is not None else time.perf_counter_ns()
        self.supervisor.emergency_stop({})
        self._enter_phase()

    def reset(self) -> None:
        self.supervisor.reset()
        if self.hal.state is HalState.ESTOP:
            self.hal.reset_estop()
        elif self.hal.state is HalState.FAULT:
            self.hal.reset_fault()
        self.source = None
        self.estop_latency_ms = None
        self.session_start_ns = None

    def heartbeat(self) -> None:
        self.supervisor.heartbeat()

    def service_lost(self) -> None:
        """The command channel closed: nobody is watching, stop now rather than wait for the watchdog."""
        self.supervisor.controlled_stop(StopReason.SERVICE_LOST, {})

    def recording_failed(self, details: dict[str, Any]) -> None:
        """The run can no longer be recorded: a controlled stop (motion nobody records must not go on)."""
        self.supervisor.controlled_stop(StopReason.RECORDING_FAILED, details)

    def latch_fault(self, reason: StopReason, details: dict[str, Any]) -> None:
        """A stop that happened outside this worker (its predecessor or the daemon died during a run):
        latched as a fault, drives off, until a therapist resets."""
        self._fault(reason, details)

    # --- the tick ---------------------------------------------------------------------------------

    def tick(self, lateness_ns: int) -> None:
        """One control period. Never raises: errors become a fault and an event."""
        self.tick_index += 1
        self.tick_ns = time.perf_counter_ns()
        self.tick_time_s = (self.tick_ns - self.start_ns) * 1e-9
        if self.session_start_ns is not None:
            self.session_time_s = (self.tick_ns - self.session_start_ns) * 1e-9
        self.skipped_ticks = lateness_ns // self.period_ns if lateness_ns > 0 else 0
        self.wrote_this_tick = False
        late = lateness_ns > LATE_THRESHOLD_NS
        if late:
            self.deadline_misses += 1
        self.supervisor.advance_watchdog(self.period_s)
        self.supervisor.tick_lateness(late)
        try:
            if self.supervisor.phase_changed:
                self._enter_phase()
            if self.supervisor.drives_enabled:
                self._command_motion()
            if self.supervisor.drives_enabled:
                self._write()
            if self.supervisor.phase_changed and not self.supervisor.drives_enabled:
                self._enter_phase()  # the last set-point is out: drives off in this same tick
            self._read()
            self._monitor()
        except Exception as error:  # the loop must survive anything: fault and report
            self._fault(
                StopReason.INTERNAL_ERROR, {"error": repr(error), "where": traceback.format_exc(limit=3)[-300:]}
            )
        self._fill_record(lateness_ns)

    def _command_motion(self) -> None:
        self._next_pose()
        self._solve_limits()
        if self._violation[0] == 0:
            self._commit()
            return
        self._limit_hit()
        if self.supervisor.drives_enabled:
            self._enter_phase()
            self._next_pose()
            self._solve_limits()
            if self._violation[0] == 0:
                self._commit()
                return
            # Even the stop ramp breaks a limit: the drives must stop by themselves.
            self._escalate("stop ramp", self._violation_details())

    def _next_pose(self) -> None:
        """The candidate stance pose of this tick from the current phase (may move to the next phase)."""
        phase, source = self.supervisor.phase, self.source
        if source is not None and (source.transition is not None or phase is Phase.CUE):
            self.step_s = (1 + self.skipped_ticks) * self.period_s  # indexed by time: a late tick skips ahead
            source.advance(1 + self.skipped_ticks, self._candidate)
            return
        self.step_s = self.period_s
        self.phase_time_s += self.period_s
        finished = self.ramp.evaluate(self.phase_time_s)
        self._candidate[:] = self.ramp.position
        if phase in (Phase.RETURN, Phase.DECELERATE) and finished:
            self.supervisor.phase_finished()

    @property
    def segment_time_s(self) -> float:
        """Time into the current segment's samples (its cue, then its return to neutral)."""
        return self.source.segment_time_s(self.period_s) if self.source is not None else 0.0

    def _solve_limits(self) -> None:
        """IK of both robots and every limit on the candidate pose; fills `_violation`."""
        np.subtract(self._candidate, self.pose, out=self._candidate_velocity)
        self._candidate_velocity /= self.step_s
        np.subtract(self._candidate_velocity, self.velocity, out=self._candidate_acceleration)
        self._candidate_acceleration /= self.step_s
        self.kernels.command(
            self._candidate,
            self.previous_sliders,
            self.previous_slider_velocity,
            self._stroke_min,
            self._stroke_max,
            self._limits_vector,
            self._sliders,
            self._slider_velocity,
            self._slider_acceleration,
            self._violation,
            self.step_s,
        )
        if self._violation[0] != 0:
            return
        forces = self.dynamics.step(self._candidate, self._candidate_velocity, self._candidate_acceleration)
        self._predicted_force[:] = forces
        force_max = self._limits_vector[5]
        peak_axis = int(np.argmax(np.abs(forces)))
        if abs(forces[peak_axis]) > force_max:
            self._violation[:] = (LimitCode.DRIVE_FORCE, peak_axis, forces[peak_axis], force_max)

    def _commit(self) -> None:
        self.pose[:] = self._candidate
        self.velocity[:] = self._candidate_velocity
        self.acceleration[:] = self._candidate_acceleration
        self.command.positions_m[:] = self._sliders
        self.command.velocity_feedforward_m_s[:] = self._slider_velocity
        self.command.force_feedforward_n[:] = self._predicted_force
        self.previous_sliders[:] = self._sliders
        self.previous_slider_velocity[:] = self._slider_velocity

    def _violation_details(self) -> dict[str, Any]:
        code = LimitCode(int(self._violation[0]))
        axis = int(self._violation[1])
        where: str | None
        if code is LimitCode.COLLISION:  # the axis field holds the pair of parts
            where = self.kernels.collision_pair_name(axis)
        else:
            where = None if axis < 0 else self.hal.axis_name(axis)
        return {
            "limit": code.label,
            "axis": where,
            "value": float(self._violation[2]),
            "limit_value": float(self._violation[3]),
            "unit": LIMIT_UNITS[code],
            "segment": self.source.segment_index if self.source is not None else -1,
            "segment_time_s": round(self.segment_time_s, 4),
        }

    def _limit_hit(self) -> None:
        self.limit_hits += 1
        self.last_limit = LimitCode(int(self._violation[0]))
        details = self._violation_details()
        self._emit("limit_hit", details, None)
        state = self.supervisor.state
        if state in (SupervisorState.RUNNING, SupervisorState.PAUSED):
            self.supervisor.controlled_stop(StopReason.LIMIT, details)
        else:
            self._escalate(state.label, details)

    def _escalate(self, context: str, details: dict[str, Any]) -> None:
        """The motion cannot be kept within limits: quick stop in the drives."""
        if self.supervisor.state is SupervisorState.ESTOP:
            self.supervisor.phase_finished()  # straight to drives off
            self._enter_phase()
        else:
            self._fault(StopReason.LIMIT, {"context": context, **details})

    # --- phases -----------------------------------------------------------------------------------

    def _enter_phase(self) -> None:
        """Set up the phase the supervisor just entered (ramps start from the last command sent)."""
        supervisor, config = self.supervisor, self.config
        supervisor.phase_changed = False
        phase, state = supervisor.phase, supervisor.state
        self.phase_time_s = 0.0
        source = self.source
        if phase in (Phase.DISABLED, Phase.DECELERATE) and source is not None:  # a stop: no checked motion plays on
            source.abandon()
        if phase is Phase.DISABLED:
            self._drives_off(state)
            return
        if phase is Phase.APPROACH:
            self._activate_drives()
        elif source is not None and (phase is Phase.CUE or source.transition is not None):
            self._use_limits(source.limits())
        elif phase is Phase.RETURN:
            self.ramp.to_pose(self.pose, self._ramp_velocity(), self.acceleration, np.zeros(6), self._return_duration())
        elif phase is Phase.DECELERATE:
            # Braking may use the margin normal motion keeps: it is checked against the robot's own limits.
            self._use_limits(self.default_limits)
            duration = config.estop_ramp_s if state is SupervisorState.ESTOP else config.controlled_stop_s
            self.ramp.to_standstill(self.pose, self._ramp_velocity(), self.acceleration, duration)
        else:  # PARKED
            self.ramp.hold(self.pose)

    def _ramp_velocity(self) -> np.ndarray:
        return start_velocity(self.velocity, self.acceleration, self.period_s, self._ramp_start_velocity)

    def _return_duration(self) -> float:
        return self.config.return_duration_s(self.pose, self._ramp_velocity())

    def _use_limits(self, limits: SessionLimits) -> None:
        self._limits_vector = limits.kernel_vector()
        self._stroke_min, self._stroke_max = limits.stroke_min_m, limits.stroke_max_m

    def _activate_drives(self) -> None:
        """Drives on; the motion state starts from where the approach was checked from (where the platform
        stood, within `APPROACH_START_TOLERANCE`)."""
        source = self.source
        assert source is not None and source.transition is not None  # the approach
        self.hal.activate()
        self.hal.read(self.reading)
        self.kernels.measured_stance_pose(self.reading.positions_m[:6], self.measured_stance)
        self.pose[:] = source.transition.poses[0]
        # The slider-rate limits difference the commanded sliders, so they start from the command of this
        # pose: the left robot's measured sliders differ from it by tracking error (microns, but at 1 kHz a
        # micron of mismatch reads as 1 m/s² of acceleration). The FK monitor watches that error instead.
        self.kernels.sliders_for(self.pose, self.previous_sliders)
        self.previous_slider_velocity[:] = 0.0
        self.velocity[:] = 0.0
        self.acceleration[:] = 0.0
        self._use_limits(source.limits(0))

    def _drives_off(self, state: SupervisorState) -> None:
        hal = self.hal
        if state is SupervisorState.ESTOP:
            if hal.state is not HalState.ESTOP:
                hal.emergency_stop()
                self._note_estop_action("drives disabled")
            self._emit("drives_disabled", {"reason": "emergency_stop"}, None)
        elif state is SupervisorState.FAULT:
            if hal.state is not HalState.FAULT:
                hal.fault(f"supervisor: {self.supervisor.stop_reason.name.lower()}")
        elif hal.state is HalState.ACTIVE:
            hal.deactivate()
            self._emit("drives_disabled", {"reason": self.supervisor.stop_reason.name.lower()}, None)
        self.velocity[:] = 0.0
        self.acceleration[:] = 0.0

    # --- I/O and monitoring -----------------------------------------------------------------------

    def _write(self) -> None:
        try:
            self.hal.write(self.command)
        except (CommandRejectedError, HalError) as error:
            self._fault(StopReason.HAL_FAULT, {"error": str(error)})
            return
        self.wrote_this_tick = True
        if self._estop_request_ns is not None and self.supervisor.state is SupervisorState.ESTOP:
            self._note_estop_action("first stop set-point")

    def _note_estop_action(self, action: str) -> None:
        if self._estop_request_ns is None:
            return
        reached_ns = time.perf_counter_ns()  # CLOCK_MONOTONIC: comparable with the requester's clock
        latency_ms = (reached_ns - self._estop_request_ns) * 1e-6
        self._estop_request_ns = None
        self.estop_latency_ms = latency_ms
        self._emit(
            "estop_reached_hal", {"action": action, "latency_ms": round(latency_ms, 4), "hal_ns": reached_ns}, None
        )

    def _read(self) -> None:
        if self.hal.state is HalState.UNCONFIGURED:
            return
        self.hal.read(self.reading)
        if self.hal.state is HalState.FAULT and self.supervisor.state not in (
            SupervisorState.FAULT,
            SupervisorState.ESTOP,
        ):
            self.supervisor.fault(StopReason.HAL_FAULT, {"hal_fault": self.hal.last_fault})
            self._enter_phase()

    def _monitor(self) -> None:
        reading = self.reading
        if self.wrote_this_tick:
            np.subtract(self.command.positions_m, reading.positions_m, out=self._tracking)
            np.abs(self._tracking, out=self._tracking)
            self.tracking_error_m = float(self._tracking.max())
            if self.tracking_error_m > self.config.tracking_error_max_m:
                self.supervisor.controlled_stop(
                    StopReason.TRACKING_ERROR,
                    {"tracking_error_m": self.tracking_error_m, "limit_m": self.config.tracking_error_max_m},
                )
        try:
            self.fk_iterations = self.kernels.measured_stance_pose(reading.positions_m[:6], self.measured_stance)
        except ForwardKinematicsError as error:
            self.fk_iterations = -1
            self.supervisor.controlled_stop(StopReason.TRACKING_ERROR, {"forward_kinematics": str(error)})
        monitor = self.fall_monitor
        if monitor is not None and self.supervisor.state in (SupervisorState.RUNNING, SupervisorState.PAUSED):
            events = monitor.step(
                self.session_time_s,
                reading.plate_force_z_n,
                reading.plate_cop_m,
                reading.harness_load_n,
                self.acceleration[2],  # the commanded heave: the plates' load swing it makes is no body drop
            )
            for event in events:
                self._emit(
                    "fall", {"onset_s": event.onset_s, "detected_s": event.detected_s, **event.values}, event.detector
                )
                self.supervisor.controlled_stop(StopReason.FALL, {"detector": event.detector})

    def _fault(self, reason: StopReason, details: dict[str, Any]) -> None:
        if self.hal.state not in (HalState.FAULT, HalState.ESTOP, HalState.UNCONFIGURED):
            self.hal.fault(f"{reason.name.lower()}: {details}")
        self.supervisor.fault(reason, details)
        self.supervisor.phase_changed = False
        self.velocity[:] = 0.0
        self.acceleration[:] = 0.0

    def _supervisor_event(self, kind: str, details: dict[str, Any]) -> None:
        self._emit(kind, details, None)

    def _emit(self, kind: str, details: dict[str, Any], detector: str | None) -> None:
        """Every event carries the time into the session on the session clock (null outside a session)."""
        session_time_s = round(self.session_time_s, 6) if self.session_start_ns is not None else None
        self._emit_to_worker(kind, {**details, "session_time_s": session_time_s}, detector)

    # --- telemetry --------------------------------------------------------------------------------

    def _record_view(self, name: str) -> np.ndarray:
        return self.record[name][0]

    def _fill_record(self, lateness_ns: int) -> None:
        record, supervisor = self.record, self.supervisor
        record["tick"] = self.tick_index
        record["time_s"] = self.tick_time_s
        record["session_time_s"] = self.session_time_s if self.session_start_ns is not None else 0.0
        record["skipped_ticks"] = min(self.skipped_ticks, 65535)
        record["utc_s"] = time.time()
        record["state"] = supervisor.state
        record["hal_state"] = HAL_STATE_CODES[self.hal.state]
        record["stop_reason"] = supervisor.stop_reason
        record["estop_latched"] = supervisor.estop_latched
        playing = supervisor.state in (SupervisorState.RUNNING, SupervisorState.PAUSED)
        source = self.source
        cue = source.cue() if playing and source is not None and supervisor.phase is Phase.CUE else None
        if cue is not None:
            self._cue_force[:] = cue[:3]
            self._cue_angular[:] = cue[3:]
        else:
            self._cue_force.fill(0.0)
            self._cue_angular.fill(0.0)
        record["plan_index"] = source.plan_index if cue is not None and source is not None else -1
        record["segment"] = source.segment_index if playing and source is not None else -1
        record["segment_time_s"] = self.segment_time_s
        record["harness_load_n"] = self.reading.harness_load_n
        record["tracking_error_m"] = self.tracking_error_m
        record["fk_iterations"] = self.fk_iterations
        record["lateness_us"] = lateness_ns * 1e-3
        record["deadline_misses"] = self.deadline_misses
        record["late_streak"] = supervisor.late_streak
        record["limit_hits"] = self.limit_hits
        record["limit_code"] = self.last_limit
        record["fall_detected"] = self.fall_monitor is not None and self.fall_monitor.fallen


# A short session that reaches every compiled kernel of the tick: IK and limits, dynamics, the simulated
# patient, FK, and the emergency-stop deceleration (the plan's washout and shaping run when it is built).
_COMPILE_PRESCRIPTION = {
    "segments": [{"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.3, "frequency_hz": 0.5}, "duration_s": 5.0}]
}
_COMPILE_PATIENT = {"body_mass_kg": 70.0, "height_m": 1.70}


def start_along_checked_approach(pipeline: TickPipeline) -> None:
    """Start a pipeline whose plan is loaded along the approach checked here from where its platform stands
    (one idle tick reads it). For in-process sessions (tests, benchmarks, compiling the tick path): the
    robot's worker never checks anything in its loop; the daemon sends it the checked approach."""
    from core.plan.check import checked_approach

    assert pipeline.source is not None, "load a plan first"
    pipeline.tick(0)
    pipeline.start(checked_approach(pipeline.source.plan, pipeline.twin, pipeline.measured_stance))


def ideal_session(
    twin: TwinRobot,
    control_rate_hz: int,
    config: SupervisorConfig,
    prescription: dict[str, Any],
    patient: dict[str, Any],
) -> TickPipeline:
    """A pipeline on an ideal (kinematic) HAL with `prescription` loaded and motion started (its approach
    checked), ticked by the caller: for compiling the tick path and for timing it. The plan itself is not
    checked here (this HAL moves nothing); the robot's worker takes only checked plans."""
    from core.plan.build import plan_prescription
    from server.hal.kinematic import KinematicHal

    hal = KinematicHal(twin, 1.0 / control_rate_hz, communication_timeout_s=60.0)
    hal.configure()
    hal.home()
    pipeline = TickPipeline(twin, hal, control_rate_hz, config, lambda *_: None)
    pipeline.load(
        plan_prescription(prescription, twin, control_rate_hz=control_rate_hz, config=config, patient=patient)
    )
    pipeline.heartbeat()
    start_along_checked_approach(pipeline)
    return pipeline


def compile_tick_path(twin: TwinRobot, control_rate_hz: int, config: SupervisorConfig) -> None:
    """Run a throwaway session on an ideal HAL so that every compiled per-tick kernel is compiled, or loaded
    from numba's cache, before the worker's loop starts. Compiling inside a tick stalls it for up to seconds
    on a fresh install: long enough for the drives' own communication-loss stop, or to delay an emergency stop.
    """
    pipeline = ideal_session(twin, control_rate_hz, config, _COMPILE_PRESCRIPTION, _COMPILE_PATIENT)
    for _ in range(round((config.soft_start_s + 1.5) * control_rate_hz)):  # approach, soft start, some cue
        pipeline.heartbeat()
        pipeline.tick(0)
    pipeline.emergency_stop(time.perf_counter_ns())
    for _ in range(round((config.estop_ramp_s + 0.1) * control_rate_hz)):
        pipeline.heartbeat()
        pipeline.tick(0)
    pipeline.hal.shutdown()
