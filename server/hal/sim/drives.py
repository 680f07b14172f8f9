"""Emulated servo drives for the twelve slider axes: what a CiA 402 drive does on its own.

Per axis, at the physics rate: a cascaded position loop (P, with velocity feed-forward) → velocity limit →
velocity loop (PI, with force feed-forward and anti-windup) → force (current) limit, the limit applied by
MuJoCo's actuator force range. Power off engages the
holding brake (a stiff spring-damper with its own force limit). A quick stop ramps the reference speed
down at the quick-stop deceleration and then holds. Heartbeat loss is each drive's own fault reaction:
the quick-stop ramp, then FAULT with the brake on. State per axis is `server.hal.base.DriveState`, changed
only through the CiA 402 transition table (`cia402.DriveStateMachines`): the compiled loop reports where a
ramp ended, and the table decides the state that follows.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from server.hal.base import AXIS_COUNT, DriveState
from server.hal.canopen.cia402 import DriveStateMachines


@dataclass(frozen=True)
class ServoParameters:
    # The cascade on an axis of effective mass m, m·s³ + kv·s² + kv·(kp + ki)·s + kv·ki·kp, is stable (Routh)
    # only while m < kv·(1/kp + 1/ki): 1333 kg at kv 20 000, ki 20. A mode's effective mass in slider
    # coordinates is many times the payload (a cantilevered foot, a tall body), and a 120 kg patient's half-body
    # per platform already rang at ~9.5 Hz. These gains give 3500 kg: still up to the paper's 250 kg rated load.
    position_gain_per_s: float = 60.0  # position loop: commanded speed per metre of error
    velocity_gain_n_s_m: float = 30_000.0  # velocity loop P
    velocity_integral_per_s: float = 10.0  # velocity loop I, as a corner frequency (rad/s)
    velocity_limit_m_s: float = 1.5
    force_limit_n: float = 4000.0  # the current limit times the force constant
    quick_stop_deceleration_m_s2: float = 10.0
    brake_stiffness_n_m: float = 5.0e6  # a locked motor shaft through the belt or screw
    brake_damping_n_s_m: float = 50_000.0  # implicit in MuJoCo (affine actuator bias), so it may be stiff
    brake_force_limit_n: float = 8000.0

    def __post_init__(self) -> None:
        for name, value in self.__dict__.items():
            if not (np.isfinite(value) and value > 0.0):
                raise ValueError(f"servo.{name} = {value!r}: must be a finite number > 0")


ENABLED = int(DriveState.OPERATION_ENABLED)
QUICK_STOP = int(DriveState.QUICK_STOP_ACTIVE)
FAULT_REACTION = int(DriveState.FAULT_REACTION_ACTIVE)
_STOPPING = np.array([DriveState.QUICK_STOP_ACTIVE, DriveState.FAULT_REACTION_ACTIVE], dtype=np.int8)


class ServoDrives:
    """Twelve emulated drives; all arrays (12,), preallocated, updated in place."""

    def __init__(self, params: ServoParameters) -> None:
        self.params = params
        self.machines = DriveStateMachines(AXIS_COUNT)  # boots into SWITCH ON DISABLED
        self.states = self.machines.states  # the same array: the loop reads it, only the table writes it
        self.target_m = np.zeros(AXIS_COUNT)
        self.velocity_feedforward_m_s = np.zeros(AXIS_COUNT)
        self.force_feedforward_n = np.zeros(AXIS_COUNT)
        self.brake_position_m = np.zeros(AXIS_COUNT)
        self.reference_velocity_m_s = np.zeros(AXIS_COUNT)
        self.integrator_n = np.zeros(AXIS_COUNT)
        self.forces_n = np.zeros(AXIS_COUNT)
        self.ctrl = np.zeros(AXIS_COUNT)
        self.bias = np.zeros((AXIS_COUNT, 3))
        self.force_range_n = np.full(AXIS_COUNT, params.force_limit_n)
        self.disable_after_stop = np.zeros(AXIS_COUNT, dtype=bool)
        self.ramp_done = np.zeros(AXIS_COUNT, dtype=bool)
        self._scratch = np.zeros(AXIS_COUNT)
        self._command = np.zeros(AXIS_COUNT)
        self._gains = np.array(
            [
                params.position_gain_per_s,
                params.velocity_gain_n_s_m,
                params.velocity_integral_per_s,
                params.velocity_limit_m_s,
                params.force_limit_n,
                params.quick_stop_deceleration_m_s2,
                params.brake_stiffness_n_m,
                params.brake_damping_n_s_m,
                params.brake_force_limit_n,
            ]
        )

    # --- CiA 402 transitions (every axis at once, through the table) -----------------------------------

    def enable(self, positions_m: np.ndarray) -> None:
        """Shutdown, switch on, enable operation (transitions 2, 3, 4), holding the present position."""
        self.target_m[:] = positions_m
        self.velocity_feedforward_m_s[:] = 0.0
        self.force_feedforward_n[:] = 0.0
        self.integrator_n[:] = 0.0
        self.disable_after_stop[:] = False
        self.machines.command(DriveState.OPERATION_ENABLED)

    def disable(self, positions_m: np.ndarray) -> None:
        """Disable voltage: brake on where the axis stands (axes still ramping finish their stop first)."""
        stopping = np.isin(self.states, _STOPPING)
        self.disable_after_stop |= stopping
        moving = ~stopping & (self.states == DriveState.OPERATION_ENABLED)
        self.brake_position_m[moving] = positions_m[moving]
        self.machines.disable(~stopping)

    def quick_stop(self, positions_m: np.ndarray, velocities_m_s: np.ndarray, *, fault: bool = False) -> None:
        """Start the quick-stop ramp on every enabled axis (transition 11; with `fault`, the fault reaction
        of transition 13, and a drive with power off faults at once, brake on)."""
        enabled = self.states == DriveState.OPERATION_ENABLED
        self.target_m[enabled] = positions_m[enabled]
        self.reference_velocity_m_s[enabled] = velocities_m_s[enabled]
        self.velocity_feedforward_m_s[enabled] = 0.0
        self.force_feedforward_n[enabled] = 0.0
        if not fault:
            self.machines.quick_stop(enabled)
            return
        idle = ~enabled & ~np.isin(self.states, _STOPPING)
        self.machines.fault(enabled | idle)
        self.machines.internal(DriveState.FAULT_REACTION_ACTIVE, DriveState.FAULT, idle)

    def reset_fault(self, positions_m: np.ndarray) -> None:
        """Fault reset and disable voltage: every axis SWITCH ON DISABLED, braked where it stands (an axis
        still in its fault reaction finishes it first: the table has no commanded way out)."""
        powered = (self.states >= ENABLED) & (self.states <= FAULT_REACTION)
        self.brake_position_m[powered] = positions_m[powered]
        self.reference_velocity_m_s[:] = 0.0
        self.disable_after_stop[:] = False
        self.machines.command(DriveState.SWITCH_ON_DISABLED, reset_faults=True)

    def _end_ramps(self) -> None:
        """Ramps the loop finished this step: the fault reaction ends in FAULT (14), a quick stop with a
        pending disable in SWITCH ON DISABLED (12, the disable held until standstill), brake on."""
        done = self.ramp_done
        self.machines.internal(DriveState.FAULT_REACTION_ACTIVE, DriveState.FAULT, done)
        self.machines.command(DriveState.SWITCH_ON_DISABLED, done & self.disable_after_stop)
        self.disable_after_stop[done] = False
        done[:] = False

    def set_command(self, positions_m: np.ndarray, velocity_ff: np.ndarray, force_ff: np.ndarray) -> None:
        enabled = self.states == DriveState.OPERATION_ENABLED
        np.copyto(self.target_m, positions_m, where=enabled)
        np.copyto(self.velocity_feedforward_m_s, velocity_ff, where=enabled)
        np.copyto(self.force_feedforward_n, force_ff, where=enabled)

    # --- the loops ---------------------------------------------------------------------------------------

    def update(self, positions_m: np.ndarray, velocities_m_s: np.ndarray, dt: float) -> None:
        """This physics step's actuator inputs: `ctrl` (12,), affine `bias` (12, 3) = (b0, b1, b2) so that
        force = ctrl + b0 + b1·x + b2·ẋ, and `force_range_n` (12,). Advances the quick-stop ramps.

        The velocity loop's proportional damping and the brake's spring-damper go in the bias, where the
        implicit integrator treats them implicitly; `forces_n` is the force this gives at the present state."""
        _servo_step(
            self.states,
            self.target_m,
            self.velocity_feedforward_m_s,
            self.force_feedforward_n,
            self.reference_velocity_m_s,
            self.integrator_n,
            self.brake_position_m,
            self.disable_after_stop,
            positions_m,
            velocities_m_s,
            self._gains,
            dt,
            self.ctrl,
            self.bias,
            self.force_range_n,
            self.forces_n,
            self.ramp_done,
        )
        if self.ramp_done.any():
            self._end_ramps()


@numba.njit(cache=True)
def _servo_step(
    states: np.ndarray,
    target: np.ndarray,
    velocity_ff: np.ndarray,
    force_ff: np.ndarray,
    ramp_velocity: np.ndarray,
    integrator: np.ndarray,
    brake_position: np.ndarray,
    disable_after_stop: np.ndarray,
    positions: np.ndarray,
    velocities: np.ndarray,
    gains: np.ndarray,
    dt: float,
    ctrl: np.ndarray,
    bias: np.ndarray,
    force_range: np.ndarray,
    forces: np.ndarray,
    ramp_done: np.ndarray,
) -> None:
    """One physics step of every axis; `ramp_done[axis]` is set where a ramp that ends in power off (fault
    reaction, quick stop with a pending disable) reached standstill: the brake holds it from this step, and
    the caller changes the state through the transition table."""
    kp, kv, ki, v_max, f_max, decel, k_brake, c_brake, f_brake = gains
    for axis in range(states.shape[0]):
        state = states[axis]
        powered = state in (ENABLED, QUICK_STOP, FAULT_REACTION)
        if state in (QUICK_STOP, FAULT_REACTION):
            speed = max(abs(ramp_velocity[axis]) - decel * dt, 0.0)
            ramp_velocity[axis] = np.sign(ramp_velocity[axis]) * speed
            target[axis] += ramp_velocity[axis] * dt
            if speed == 0.0 and (state == FAULT_REACTION or disable_after_stop[axis]):
                brake_position[axis] = positions[axis]
                ramp_done[axis] = True
                powered = False
        if powered:
            command = kp * (target[axis] - positions[axis]) + velocity_ff[axis] + ramp_velocity[axis]
            command = min(max(command, -v_max), v_max)
            error = command - velocities[axis]
            force = kv * error + integrator[axis] + force_ff[axis]
            if abs(force) < f_max:  # anti-windup: integrate only while unsaturated
                integrator[axis] += kv * ki * dt * error
            ctrl[axis] = kv * command + integrator[axis] + force_ff[axis]
            bias[axis, 0], bias[axis, 1], bias[axis, 2] = 0.0, 0.0, -kv
            force_range[axis] = f_max
            forces[axis] = min(max(force, -f_max), f_max)
        else:  # power off: the holding brake
            integrator[axis] = 0.0
            ctrl[axis] = 0.0
            bias[axis, 0], bias[axis, 1], bias[axis, 2] = k_brake * brake_position[axis], -k_brake, -c_brake
            force_range[axis] = f_brake
            force = -k_brake * (positions[axis] - brake_position[axis]) - c_brake * velocities[axis]
            forces[axis] = min(max(force, -f_brake), f_brake)
