"""The `sim` HAL backend: lifecycle, refusals that never reach a drive, servo dynamics, drive reactions."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from core.dynamics import PayloadModel
from core.patient import PatientParameters
from core.physics import GRAVITY_M_S2
from core.robot import TwinRobot, named_twin
from server.hal.base import CommandRejectedError, DriveState, HalCommand, HalError, HalReading, HalState
from server.hal.sim.backend import SimHal
from server.hal.sim.drives import ServoParameters

PERIOD_S = 0.001


def _active(twin: TwinRobot, **options: object) -> tuple[SimHal, HalReading, HalCommand]:
    hal = SimHal(twin, PERIOD_S, **options)  # type: ignore[arg-type]
    hal.configure()
    hal.home()
    hal.activate()
    reading, command = HalReading(), HalCommand()
    hal.read(reading)
    command.positions_m[:] = reading.positions_m
    return hal, reading, command


@pytest.fixture
def active(twin: TwinRobot) -> Iterator[tuple[SimHal, HalReading, HalCommand]]:
    hal, reading, command = _active(twin)
    yield hal, reading, command
    hal.shutdown()


def _run(hal: SimHal, reading: HalReading, command: HalCommand, ticks: int) -> np.ndarray:
    """Write the same command and read, `ticks` times; slider positions (ticks, 12)."""
    positions = np.empty((ticks, 12))
    for tick in range(ticks):
        hal.write(command)
        hal.read(reading)
        positions[tick] = reading.positions_m
    return positions


def test_lifecycle_and_drive_states(twin: TwinRobot) -> None:
    hal = SimHal(twin, PERIOD_S)
    reading = HalReading()
    with pytest.raises(HalError):
        hal.read(reading)
    hal.configure()
    hal.read(reading)
    assert hal.state is HalState.CONFIGURED
    assert np.all(reading.drive_states == DriveState.SWITCH_ON_DISABLED)  # as every backend (CiA 402 table)
    assert not reading.homed.any()
    hal.home()
    hal.activate()
    hal.read(reading)
    assert np.all(reading.drive_states == DriveState.OPERATION_ENABLED) and reading.homed.all()
    assert reading.hardware_time_s == pytest.approx(2 * PERIOD_S)  # one period per read()
    hal.deactivate()
    held = reading.positions_m.copy()
    for _ in range(200):  # brakes on: the platforms stay where they were
        hal.read(reading)
    assert hal.state is HalState.CONFIGURED
    assert np.all(reading.drive_states == DriveState.SWITCH_ON_DISABLED)  # as every backend (CiA 402 table)
    assert np.max(np.abs(reading.positions_m - held)) < 3e-4
    hal.shutdown()
    assert hal.state is HalState.UNCONFIGURED


def test_readings_carry_the_patient_on_the_force_plates(active: tuple[SimHal, HalReading, HalCommand]) -> None:
    hal, reading, command = active
    _run(hal, reading, command, 300)
    np.testing.assert_allclose(reading.plate_force_z_n, [37.5 * GRAVITY_M_S2] * 2, rtol=0.01)
    assert np.max(np.abs(reading.plate_cop_m)) < 0.005
    assert reading.harness_load_n == 0.0  # the rope is slack while standing


@pytest.mark.parametrize(
    ("axis", "change", "expected_field"),
    [
        (3, "outside_stroke", "positions_m[right slider 4]"),
        (8, "jump", "positions_m[left slider 3]"),
        (0, "nan", "positions_m[right slider 1]"),
        (11, "nan_force", "force_feedforward_n[left slider 6]"),
    ],
)
def test_bad_commands_are_refused_and_never_reach_the_drives(
    active: tuple[SimHal, HalReading, HalCommand], axis: int, change: str, expected_field: str
) -> None:
    hal, reading, command = active
    _run(hal, reading, command, 5)
    held = reading.positions_m.copy()
    bad = HalCommand()
    bad.positions_m[:] = command.positions_m
    if change == "outside_stroke":
        bad.positions_m[axis] = hal.stroke_max_m[axis] + 0.001
    elif change == "jump":
        bad.positions_m[axis] += 2.0 * hal.max_step_m
    elif change == "nan":
        bad.positions_m[axis] = np.nan
    else:
        bad.force_feedforward_n[axis] = np.nan
    with pytest.raises(CommandRejectedError) as error:
        hal.write(bad)
    assert error.value.field == expected_field
    assert hal.state is HalState.FAULT and expected_field in (hal.last_fault or "")
    # The drives quick-stop where they stand: the refused value never became a target.
    targets = hal.drive_targets_m
    assert np.all(np.isfinite(targets)) and np.max(np.abs(targets - held)) < 1e-4
    hal.read(reading)
    assert np.all(reading.drive_states == DriveState.QUICK_STOP_ACTIVE)
    with pytest.raises(HalError):
        hal.write(command)  # nothing more is sent until the fault is reset


def test_fault_reset_returns_to_configured_with_brakes(active: tuple[SimHal, HalReading, HalCommand]) -> None:
    hal, reading, command = active
    command.positions_m[0] = np.nan
    with pytest.raises(CommandRejectedError):
        hal.write(command)
    hal.reset_fault()
    hal.read(reading)
    assert hal.state is HalState.CONFIGURED
    assert np.all(reading.drive_states == DriveState.SWITCH_ON_DISABLED)  # as every backend (CiA 402 table)


def _step_response(twin: TwinRobot, servo: ServoParameters, step_m: float, ticks: int) -> tuple[np.ndarray, HalReading]:
    hal, reading, command = _active(twin, servo=servo)
    start = reading.positions_m.copy()
    command.positions_m += step_m
    positions = _run(hal, reading, command, ticks)
    return (positions - start) / step_m, reading


# The servo-dynamics bands below were calibrated on the layout before issue 13 (feet 0.25 m inboard of each
# platform). On today's default (feet cantilevered 0.68 m) the sliders carry more of the patient's moment
# (static drive force up to 583 N instead of 338 N): slider 5 reaches 0.48 of a step at one time constant
# and a force-limited step settles to 0.18 mm in 200 ms. The servo model is the subject here, so these
# keep the calibration layout (MuJoCo contacts are off by default, so its crossing rods do not matter).
SERVO_CALIBRATION_TWIN = named_twin("legacy-interleaved")


def test_sim_reaches_commanded_positions_with_the_configured_servo_dynamics() -> None:
    twin = SERVO_CALIBRATION_TWIN
    servo = ServoParameters(position_gain_per_s=60.0)
    response, _ = _step_response(twin, servo, 0.001, 400)
    time_constant_ticks = round(1.0 / servo.position_gain_per_s / PERIOD_S)
    # The position loop is first order at 1/kp = 16.7 ms, shaped by the velocity loop and the load.
    assert np.all((response[time_constant_ticks] > 0.5) & (response[time_constant_ticks] < 0.85))
    assert np.max(np.abs(response[300:] - 1.0)) < 0.05  # within 50 µm of the set-point
    slower, _ = _step_response(twin, ServoParameters(position_gain_per_s=20.0), 0.001, 400)
    assert np.all(slower[time_constant_ticks] < response[time_constant_ticks] - 0.2)


def test_drive_velocity_and_force_limits_hold() -> None:
    servo = ServoParameters(velocity_limit_m_s=0.02, force_limit_n=1500.0)
    hal, reading, command = _active(SERVO_CALIBRATION_TWIN, servo=servo)
    start = reading.positions_m.copy()
    command.positions_m += 0.0015
    progress, peak_force = [], 0.0
    for _ in range(200):
        hal.write(command)
        hal.read(reading)
        progress.append(np.min((reading.positions_m - start) / 0.0015))
        peak_force = max(peak_force, float(np.max(np.abs(reading.drive_forces_n))))
    # Unlimited, the position loop would ask 60/s × 1.5 mm = 0.09 m/s and be 90 % there in ~40 ms;
    # at 0.02 m/s the 1.35 mm take at least 67 ms.
    reached = int(np.argmax(np.asarray(progress) >= 0.9))
    assert reached * PERIOD_S >= 0.9 * 0.0015 / 0.02
    assert peak_force <= 1500.0
    assert np.max(np.abs(reading.positions_m - start - 0.0015)) < 1e-4


def test_drives_stop_by_themselves_when_set_points_stop(twin: TwinRobot) -> None:
    hal, reading, command = _active(twin, communication_timeout_s=0.02)
    velocity = 0.2  # m/s on every slider along +x: a small, consistent platform motion
    for _ in range(60):  # moving, with a fresh set-point each tick: no reaction
        command.positions_m += velocity * PERIOD_S
        command.velocity_feedforward_m_s[:] = velocity
        hal.write(command)
        hal.read(reading)
    assert hal.state is HalState.ACTIVE and np.all(reading.drive_states == DriveState.OPERATION_ENABLED)
    assert np.min(reading.velocities_m_s) > 0.1
    states, speeds = [], []
    for _ in range(200):  # the worker goes silent; the drives keep running on their own clock
        hal.read(reading)
        states.append(reading.drive_states.copy())
        speeds.append(np.max(np.abs(reading.velocities_m_s)))
    assert hal.state is HalState.FAULT and "communication lost" in (hal.last_fault or "")
    reacted = [i for i, s in enumerate(states) if np.all(s == DriveState.FAULT_REACTION_ACTIVE)]
    assert reacted and 18 <= reacted[0] <= 21  # at the 20 ms timeout (one tick since the last write)
    assert np.all(states[-1] == DriveState.FAULT)
    assert speeds[-1] < 1e-3  # stopped and braked


def test_emergency_stop_ramps_down_then_removes_power(twin: TwinRobot) -> None:
    hal, reading, command = _active(twin)
    for _ in range(60):
        command.positions_m += 0.2 * PERIOD_S
        command.velocity_feedforward_m_s[:] = 0.2
        hal.write(command)
        hal.read(reading)
    hal.emergency_stop()
    assert hal.state is HalState.ESTOP
    hal.read(reading)
    assert np.all(reading.drive_states == DriveState.QUICK_STOP_ACTIVE)  # category 1: controlled stop first
    for _ in range(100):
        hal.read(reading)
    assert np.all(reading.drive_states == DriveState.SWITCH_ON_DISABLED)
    assert np.max(np.abs(reading.velocities_m_s)) < 1e-3
    hal.reset_estop()
    assert hal.state is HalState.CONFIGURED
    with pytest.raises(HalError):
        hal.write(command)  # a reset never restarts motion


def test_simulated_patient_loads_the_plates(twin: TwinRobot) -> None:
    class Setup:
        parameters = PatientParameters.preset("healthy", 70.0, 1.75)
        seed = 3

    hal = SimHal(twin, PERIOD_S)
    hal.configure()
    hal.attach_patient(Setup())
    hal.home()
    hal.activate()
    reading, command = HalReading(), HalCommand()
    hal.read(reading)
    command.positions_m[:] = reading.positions_m
    start = reading.positions_m.copy()
    _run(hal, reading, command, 500)
    assert reading.plate_force_z_n.sum() == pytest.approx(70.0 * GRAVITY_M_S2, rel=0.05)
    assert np.max(np.abs(reading.positions_m - start)) < 2e-4  # the drives carry the patient's load
    with pytest.raises(HalError):
        hal.attach_patient(None)  # not while active


def test_the_drives_hold_the_rated_load_still(twin: TwinRobot) -> None:
    """The cascade (position P, velocity PI) is stable only while an axis's effective mass stays below
    kv·(1/kp + 1/ki). Tuned for the 75 kg design point, the drives let a 120 kg patient's half-body on each
    platform oscillate at ~9.5 Hz, growing into the force limit within 15 s of standing still. The paper's
    rated load is 250 kg; up to it the platform must hold still."""
    payload = PayloadModel.from_body(250.0, 1.75)
    hal, reading, command = _active(twin, payload=payload)
    positions = _run(hal, reading, command, 15_000)
    swing_mm = 1e3 * float(np.max(np.ptp(positions[-3000:], axis=0)))  # over the last 3 s, worst axis
    assert swing_mm < 0.01, f"the sliders still swing {swing_mm:.3f} mm peak to peak after 12 s"
    assert np.max(np.abs(reading.drive_forces_n)) < 0.9 * hal.simulator.drives.params.force_limit_n
    hal.shutdown()
