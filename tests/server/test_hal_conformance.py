"""One hardware contract: the same lifecycle on every backend gives the same HAL states and drive states.

configure → home → activate → read/write (the axes follow) → a rejected command faults the HAL (quick
stop) → reset → activate → emergency stop (latched; drives end SWITCH ON DISABLED; reset never moves)
→ activate → deactivate. After each step every backend must report the same HAL state and the same CiA
402 state on every axis. The canopen backend runs twelve simulated drives on python-can's virtual bus.
"""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import uuid
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from core.patient import PatientParameters
from core.physics import GRAVITY_M_S2
from core.robot import TwinRobot
from server.hal.base import (
    AXIS_COUNT,
    CommandRejectedError,
    DriveState,
    HalCommand,
    HalError,
    HalReading,
    HalState,
    HardwareInterface,
)
from tests.server.canopen_fixtures import brisk_configuration, no_leaked_threads  # noqa: F401 (autouse fixture)

BACKENDS = ("kinematic", "sim", "canopen")
SETTLE_TICKS = 2000  # generous: a 1.5 m/s axis quick-stops within a few hundred ticks on every backend


def make_backend(name: str, twin: TwinRobot) -> HardwareInterface:
    if name == "kinematic":
        from server.hal.kinematic import KinematicHal

        # The kinematic drives' communication-loss stop runs on wall time: generous on a loaded machine.
        return KinematicHal(twin, 0.001, communication_timeout_s=5.0)
    if name == "sim":
        from server.hal.sim.backend import SimHal

        return SimHal(twin, 0.001)
    from server.hal.canopen.master import create_canopen_hal

    channel = f"ssp-conformance-{uuid.uuid4().hex[:10]}"
    return create_canopen_hal(twin, 0.002, "virtual", channel, configuration=brisk_configuration(), simulate=AXIS_COUNT)


@pytest.fixture(params=BACKENDS)
def hal(request: pytest.FixtureRequest, twin: TwinRobot) -> Iterator[HardwareInterface]:
    backend = make_backend(request.param, twin)
    yield backend
    backend.shutdown()


def tick(hal: HardwareInterface, reading: HalReading, command: HalCommand | None = None) -> None:
    """One worker tick: write while ACTIVE, then read (the canopen read waits for this cycle's answers)."""
    if command is not None and hal.state is HalState.ACTIVE:
        hal.write(command)
    hal.wait_for_feedback(1.0)  # lock-step on the bus: the reading is this cycle's
    hal.read(reading)


def read_until(hal: HardwareInterface, reading: HalReading, done: Callable[[HalReading], bool]) -> bool:
    for _ in range(SETTLE_TICKS):
        tick(hal, reading)
        if done(reading):
            return True
    return False


def all_in(state: DriveState) -> Callable[[HalReading], bool]:
    return lambda reading: bool(np.all(reading.drive_states == state))


def states_of(reading: HalReading) -> list[str]:
    return sorted({DriveState(int(s)).name for s in reading.drive_states})


def assert_drives(hal: HardwareInterface, reading: HalReading, state: DriveState) -> None:
    assert read_until(hal, reading, all_in(state)), f"drives report {states_of(reading)}, expected {state.name}"


def inward_command(reading: HalReading, hal: HardwareInterface) -> HalCommand:
    """A command at the measured positions, to be stepped towards mid-stroke."""
    command = HalCommand()
    command.positions_m[:] = reading.positions_m
    return command


def enabled(hal: HardwareInterface) -> tuple[HalReading, HalCommand]:
    """Configure, home and activate; the first reading and a command holding the axes where they are."""
    reading = HalReading()
    hal.configure()
    hal.home()
    hal.activate()
    tick(hal, reading)
    return reading, inward_command(reading, hal)


def move_towards_mid_stroke(hal: HardwareInterface, reading: HalReading, ticks: int) -> np.ndarray:
    """Ramp every axis towards mid-stroke at 0.05 m/s; returns the commanded displacement (m)."""
    tick(hal, reading)
    command = inward_command(reading, hal)
    start = command.positions_m.copy()
    direction = np.sign(0.5 * (hal.stroke_min_m + hal.stroke_max_m) - start)
    for _ in range(ticks):
        command.positions_m += direction * 0.05 * hal.control_period_s
        tick(hal, reading, command)
    for _ in range(200):  # hold the last set-point while the axes catch up
        tick(hal, reading, command)
    return command.positions_m - start


def test_configure_activate_read_write(hal: HardwareInterface) -> None:
    reading = HalReading()
    with pytest.raises(HalError):
        hal.read(reading)
    hal.configure()
    assert hal.state is HalState.CONFIGURED
    assert_drives(hal, reading, DriveState.SWITCH_ON_DISABLED)
    hal.home()
    tick(hal, reading)
    assert reading.homed.all()
    assert_drives(hal, reading, DriveState.SWITCH_ON_DISABLED)
    with pytest.raises(HalError):
        hal.write(HalCommand())  # not ACTIVE
    hal.activate()
    assert hal.state is HalState.ACTIVE
    assert_drives(hal, reading, DriveState.OPERATION_ENABLED)
    start = reading.positions_m.copy()
    commanded = move_towards_mid_stroke(hal, reading, 200)
    assert np.all(np.abs(commanded) > 9e-3)
    np.testing.assert_allclose(reading.positions_m - start, commanded, atol=1e-3)
    assert np.all(reading.drive_states == DriveState.OPERATION_ENABLED)


def test_rejected_command_faults_with_a_quick_stop_and_reset_leaves_power_off(hal: HardwareInterface) -> None:
    reading, command = enabled(hal)
    command.positions_m[3] = np.nan
    with pytest.raises(CommandRejectedError, match="positions_m"):
        hal.write(command)
    assert hal.state is HalState.FAULT
    assert_drives(hal, reading, DriveState.QUICK_STOP_ACTIVE)
    with pytest.raises(HalError):
        hal.activate()  # a fault must be reset first
    hal.reset_fault()
    assert hal.state is HalState.CONFIGURED
    assert_drives(hal, reading, DriveState.SWITCH_ON_DISABLED)
    hal.activate()
    assert_drives(hal, reading, DriveState.OPERATION_ENABLED)


def test_emergency_stop_latches_removes_power_and_reset_never_moves(hal: HardwareInterface) -> None:
    reading, command = enabled(hal)
    hal.emergency_stop()
    assert hal.state is HalState.ESTOP
    assert_drives(hal, reading, DriveState.SWITCH_ON_DISABLED)
    for refused in (lambda: hal.write(command), hal.activate, hal.reset_fault):
        with pytest.raises(HalError):
            refused()
    assert hal.state is HalState.ESTOP
    for _ in range(300):  # the drives' own stop ends (the sim's quick-stop ramp carries a loaded slider on)
        tick(hal, reading)
    stopped_at = reading.positions_m.copy()
    hal.reset_estop()
    assert hal.state is HalState.CONFIGURED
    for _ in range(100):
        tick(hal, reading)
    assert np.all(reading.drive_states == DriveState.SWITCH_ON_DISABLED), states_of(reading)
    np.testing.assert_allclose(reading.positions_m, stopped_at, atol=1e-4)


def test_deactivate_leaves_every_drive_switch_on_disabled(hal: HardwareInterface) -> None:
    """Defect (issue 12 §6): kinematic and sim reported READY_TO_SWITCH_ON here, canopen SWITCH_ON_DISABLED."""
    reading = HalReading()
    hal.configure()
    hal.home()
    hal.activate()
    move_towards_mid_stroke(hal, reading, 50)
    hal.deactivate()
    assert hal.state is HalState.CONFIGURED
    assert_drives(hal, reading, DriveState.SWITCH_ON_DISABLED)


@dataclasses.dataclass(frozen=True)
class Patient:
    parameters: PatientParameters
    seed: int = 0


def test_optional_capabilities_are_declared_not_probed(hal: HardwareInterface) -> None:
    """A backend either simulates a patient (then its plates carry the body) or refuses one with a HalError."""
    patient = Patient(PatientParameters.preset("healthy", 70.0, 1.75))
    hal.configure()
    assert hal.drain_events() is not None
    if not hal.simulates_patient:
        with pytest.raises(HalError, match="does not simulate a patient"):
            hal.attach_patient(patient)
        return
    hal.attach_patient(patient)
    hal.home()
    hal.activate()
    reading = HalReading()
    for _ in range(50):
        tick(hal, reading)
    body_weight_n = 70.0 * GRAVITY_M_S2
    assert 0.5 * body_weight_n < reading.plate_force_z_n.sum() < 1.5 * body_weight_n


def test_hal_imports_neither_realtime_nor_anything_that_imports_it_back() -> None:
    """The layering the package move gives: hal → core only; the MuJoCo twin lives inside hal."""
    probe = (
        "import sys\n"
        "import server.hal.base, server.hal.backends, server.hal.kinematic, server.hal.canopen.master\n"
        "import server.hal.sim.backend\n"
        "print(sorted(m for m in sys.modules if m.startswith('server.') and not m.startswith('server.hal')))\n"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]", result.stdout
