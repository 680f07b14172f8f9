"""The hardware abstraction layer: the one seam between the control core and whatever moves.

Lifecycle, after ros2_control's hardware interface:

    UNCONFIGURED --configure()--> CONFIGURED (communication up, power off)
    CONFIGURED --activate()--> ACTIVE (drives enabled, cyclic read()/write())
    ACTIVE --deactivate()--> CONFIGURED
    any --fault--> FAULT --reset_fault()--> CONFIGURED
    any --emergency_stop()--> ESTOP (quick stop, then drives disabled) --reset_estop()--> CONFIGURED

`write()` validates every command here, in the base class, before any backend sees it: a NaN, a
set-point outside the stroke or a jump beyond one tick's travel is refused with `CommandRejectedError`
(field, value, limit), nothing reaches a drive, and the HAL quick-stops into FAULT.

Optional capabilities are declared here, with a default every backend inherits, so callers never probe
for attributes: `simulates_patient` / `attach_patient()` (backends whose platforms are simulated),
`measures_patient_loads` (backends whose readings carry the force plates and the harness load cell),
`drain_events()` (bus and drive events; none by default) and `wait_for_feedback()` (for backends whose
readings arrive asynchronously; immediate by default).

Axis order: twelve axes, the right robot's sliders 1–6 then the left robot's 1–6 (REFERENCE.md order).
Positions are metres along each rail in that robot's base frame.
"""

from __future__ import annotations

import abc
import enum
from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol

import numba
import numpy as np

from core.errors import InvalidValueError
from core.patient import PatientParameters
from core.robot import TwinRobot

AXIS_COUNT = 12
FEET = ("right", "left")


COMMAND_FIELDS = ("positions_m", "velocity_feedforward_m_s", "force_feedforward_n")
# Codes of `_first_invalid_setpoint`: 1–3 a non-finite value in COMMAND_FIELDS[code − 1], then stroke, jump.
_VALID, _NOT_FINITE_LAST, _OUTSIDE_STROKE, _JUMP = 0, 3, 4, 5


@numba.njit(cache=True)
def _first_invalid_setpoint(
    positions: np.ndarray,
    velocity_feedforward: np.ndarray,
    force_feedforward: np.ndarray,
    stroke_min: np.ndarray,
    stroke_max: np.ndarray,
    reference: np.ndarray,
    max_step: float,
) -> tuple[int, int, float]:
    """(code, axis, value) of the first refusal in check order, (0, −1, 0) when the command is valid;
    for a jump, the axis with the largest one."""
    for code, values in ((1, positions), (2, velocity_feedforward), (3, force_feedforward)):
        for axis in range(values.size):
            if not np.isfinite(values[axis]):
                return code, axis, values[axis]
    for axis in range(positions.size):
        if positions[axis] < stroke_min[axis] or positions[axis] > stroke_max[axis]:
            return _OUTSIDE_STROKE, axis, positions[axis]
    worst_axis, worst_jump = -1, max_step
    for axis in range(positions.size):
        jump = abs(positions[axis] - reference[axis])
        if jump > worst_jump:
            worst_axis, worst_jump = axis, jump
    if worst_axis >= 0:
        return _JUMP, worst_axis, positions[worst_axis]
    return _VALID, -1, 0.0


class HalState(enum.Enum):
    UNCONFIGURED = "unconfigured"
    CONFIGURED = "configured"
    ACTIVE = "active"
    FAULT = "fault"
    ESTOP = "estop"


class DriveState(enum.IntEnum):
    """CiA 402 power state machine states, as every backend reports them per axis."""

    NOT_READY_TO_SWITCH_ON = 0
    SWITCH_ON_DISABLED = 1
    READY_TO_SWITCH_ON = 2
    SWITCHED_ON = 3
    OPERATION_ENABLED = 4
    QUICK_STOP_ACTIVE = 5
    FAULT_REACTION_ACTIVE = 6
    FAULT = 7


class PatientLike(Protocol):
    """What `attach_patient` needs (core.plan.build.PatientSetup has it)."""

    @property
    def parameters(self) -> PatientParameters: ...

    @property
    def seed(self) -> int: ...


class HalError(RuntimeError):
    """A lifecycle call made in the wrong state, or a backend failure."""


class CommandRejectedError(InvalidValueError):
    """A command refused before reaching any drive; names the axis field, the value and the limit."""


@dataclass
class HalCommand:
    """Set-points for one tick; preallocated once and filled in place by the worker."""

    positions_m: np.ndarray = field(default_factory=lambda: np.zeros(AXIS_COUNT))
    velocity_feedforward_m_s: np.ndarray = field(default_factory=lambda: np.zeros(AXIS_COUNT))
    force_feedforward_n: np.ndarray = field(default_factory=lambda: np.zeros(AXIS_COUNT))


@dataclass
class HalReading:
    """What one read() returns; preallocated once and filled in place by the backend."""

    positions_m: np.ndarray = field(default_factory=lambda: np.zeros(AXIS_COUNT))
    velocities_m_s: np.ndarray = field(default_factory=lambda: np.zeros(AXIS_COUNT))
    drive_forces_n: np.ndarray = field(default_factory=lambda: np.zeros(AXIS_COUNT))
    drive_states: np.ndarray = field(default_factory=lambda: np.zeros(AXIS_COUNT, dtype=np.int8))
    homed: np.ndarray = field(default_factory=lambda: np.zeros(AXIS_COUNT, dtype=bool))
    # Force plate under each foot (right, left): vertical force and centre of pressure (x, y) in the
    # foot-plate frame; harness load cell along the rope.
    plate_force_z_n: np.ndarray = field(default_factory=lambda: np.zeros(2))
    plate_cop_m: np.ndarray = field(default_factory=lambda: np.zeros((2, 2)))
    harness_load_n: float = 0.0
    monotonic_ns: int = 0  # host time.perf_counter_ns() at the read
    hardware_time_s: float = 0.0  # the backend's own clock (sim time, drive SYNC count · period)


class HardwareInterface(abc.ABC):
    """One backend for the twelve slider axes and the sensors. Subclasses implement the `_` hooks."""

    # Whether the platforms carry a simulated patient (`attach_patient`); real drives carry a real one.
    simulates_patient: ClassVar[bool] = False
    # Whether `read()` fills the force plates and the harness load cell: the fall detectors need them.
    measures_patient_loads: ClassVar[bool] = False

    def __init__(self, twin: TwinRobot, control_period_s: float) -> None:
        if not 0.0 < control_period_s <= 0.01:
            raise CommandRejectedError("control_period_s", control_period_s, "must be in (0, 0.01] s")
        self.twin = twin
        self.control_period_s = control_period_s
        self.state = HalState.UNCONFIGURED
        self.last_fault: str | None = None
        robots = [twin.robot_for(side) for side in FEET]
        self.stroke_min_m = np.concatenate([r.stroke_min_m for r in robots])
        self.stroke_max_m = np.concatenate([r.stroke_max_m for r in robots])
        # Largest set-point change one tick may ask for: the velocity limit over one period, with a
        # 10 % margin for rounding in the command path.
        self.max_step_m = 1.1 * robots[0].limits.slider_velocity_max_m_s * control_period_s
        self._last_command_m: np.ndarray | None = None
        # Compile the per-tick check now: compiling inside the first write() stalls that tick for hundreds
        # of milliseconds, long enough for the drives' own communication-loss stop.
        idle = HalCommand()
        idle.positions_m[:] = self.stroke_min_m
        _first_invalid_setpoint(*self._check_arguments(idle, self.stroke_min_m))

    # --- lifecycle ---------------------------------------------------------------------------------

    def configure(self) -> None:
        self._require(HalState.UNCONFIGURED, "configure")
        self._on_configure()
        self.state = HalState.CONFIGURED

    def activate(self) -> None:
        self._require(HalState.CONFIGURED, "activate")
        self._on_activate()
        self._last_command_m = None
        self.state = HalState.ACTIVE

    def deactivate(self) -> None:
        if self.state is HalState.ACTIVE:
            self._on_deactivate()
            self.state = HalState.CONFIGURED

    def shutdown(self) -> None:
        """Power off and close communication, from any state."""
        if self.state is HalState.ACTIVE:
            self._on_deactivate()
        if self.state is not HalState.UNCONFIGURED:
            self._on_shutdown()
        self.state = HalState.UNCONFIGURED

    def emergency_stop(self) -> None:
        """Quick stop every axis, then disable the drives. Latched until reset_estop()."""
        if self.state is not HalState.UNCONFIGURED:
            self._on_quick_stop()
            self._on_disable()
        self.state = HalState.ESTOP

    def reset_estop(self) -> None:
        """Clear the latch; drives stay disabled (CONFIGURED) so a reset never restarts motion."""
        self._require(HalState.ESTOP, "reset_estop")
        self.state = HalState.CONFIGURED

    def fault(self, reason: str) -> None:
        """Enter FAULT with a controlled quick stop; used by backends and by rejected commands."""
        self.last_fault = reason
        if self.state in (HalState.ACTIVE, HalState.CONFIGURED):
            self._on_quick_stop()
        if self.state is not HalState.ESTOP:
            self.state = HalState.FAULT

    def reset_fault(self) -> None:
        self._require(HalState.FAULT, "reset_fault")
        self._on_reset_fault()
        self.last_fault = None
        self.state = HalState.CONFIGURED

    def home(self) -> None:
        """Home every axis (CiA 402 homing on drives; immediate on the sim and kinematic backends)."""
        self._require(HalState.CONFIGURED, "home")
        self._on_home()

    # --- optional capabilities ---------------------------------------------------------------------

    def attach_patient(self, patient: PatientLike | None) -> None:
        """Put a simulated patient on the platforms (None takes it off). Only a backend that
        `simulates_patient` can: on any other this is a programming error, and it is refused."""
        raise HalError(f"attach_patient: the {type(self).__name__} backend does not simulate a patient")

    def drain_events(self) -> list[dict[str, Any]]:
        """Backend events (bus faults, drive EMCYs…) since the last drain, oldest first; none by default."""
        return []

    def wait_for_feedback(self, timeout_s: float) -> bool:
        """Block until the answers to the last cycle sent have arrived; True when they have. A backend whose
        read() computes its answer at once has nothing to wait for."""
        return True

    # --- cyclic ------------------------------------------------------------------------------------

    def read(self, out: HalReading) -> None:
        if self.state is HalState.UNCONFIGURED:
            raise HalError("read: the HAL is not configured")
        self._on_read(out)

    def write(self, command: HalCommand) -> None:
        """Validate, then send. A rejected command never reaches a drive and faults the HAL."""
        self._require(HalState.ACTIVE, "write")
        try:
            self.validate(command)
        except CommandRejectedError as rejected:
            self.fault(str(rejected))
            raise
        self._on_write(command)
        if self._last_command_m is None:
            self._last_command_m = command.positions_m.copy()
        else:
            self._last_command_m[:] = command.positions_m

    def validate(self, command: HalCommand) -> None:
        """Refuse a command with a non-finite value, a set-point outside the stroke, or a jump beyond one
        tick's travel. The checks run in one compiled call (they are on every tick's path); the message is
        built only for a refusal."""
        for name in COMMAND_FIELDS:
            values = getattr(command, name)
            if values.shape != (AXIS_COUNT,):
                raise CommandRejectedError(
                    name, float("nan"), f"expected {AXIS_COUNT} values, got shape {values.shape}"
                )
        reference = self._last_command_m if self._last_command_m is not None else self._measured_positions()
        code, axis, value = _first_invalid_setpoint(*self._check_arguments(command, reference))
        if code == _VALID:
            return
        if code <= _NOT_FINITE_LAST:
            raise CommandRejectedError(f"{COMMAND_FIELDS[code - 1]}[{self.axis_name(axis)}]", value, "must be finite")
        field_name = f"positions_m[{self.axis_name(axis)}]"
        if code == _OUTSIDE_STROKE:
            raise CommandRejectedError(
                field_name, value, f"stroke is [{self.stroke_min_m[axis]:.4f}, {self.stroke_max_m[axis]:.4f}] m"
            )
        jump_m = abs(value - reference[axis])
        raise CommandRejectedError(
            field_name,
            value,
            f"jump of {jump_m * 1e3:.3f} mm exceeds one tick's travel {self.max_step_m * 1e3:.3f} mm",
        )

    def _check_arguments(self, command: HalCommand, reference: np.ndarray) -> tuple[Any, ...]:
        return (
            command.positions_m,
            command.velocity_feedforward_m_s,
            command.force_feedforward_n,
            self.stroke_min_m,
            self.stroke_max_m,
            reference,
            self.max_step_m,
        )

    @staticmethod
    def axis_name(axis: int) -> str:
        return f"{FEET[axis // 6]} slider {axis % 6 + 1}"

    def _require(self, state: HalState, action: str) -> None:
        if self.state is not state:
            raise HalError(f"{action}: HAL is {self.state.value}, must be {state.value}")

    # --- backend hooks -----------------------------------------------------------------------------

    @abc.abstractmethod
    def _on_configure(self) -> None: ...

    @abc.abstractmethod
    def _on_activate(self) -> None: ...

    @abc.abstractmethod
    def _on_deactivate(self) -> None: ...

    @abc.abstractmethod
    def _on_quick_stop(self) -> None:
        """Bring every axis to a controlled stop (CiA 402 quick stop, 0x605A)."""

    @abc.abstractmethod
    def _on_disable(self) -> None:
        """Remove drive power (after the quick stop)."""

    @abc.abstractmethod
    def _on_reset_fault(self) -> None: ...

    @abc.abstractmethod
    def _on_home(self) -> None: ...

    @abc.abstractmethod
    def _on_read(self, out: HalReading) -> None: ...

    @abc.abstractmethod
    def _on_write(self, command: HalCommand) -> None: ...

    @abc.abstractmethod
    def _measured_positions(self) -> np.ndarray:
        """Latest measured axis positions (m), the reference for the first command's jump check."""

    def _on_shutdown(self) -> None:  # noqa: B027 — optional hook
        """Close communication; backends with a bus override it."""
