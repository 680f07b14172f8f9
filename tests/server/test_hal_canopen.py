"""The `canopen` HAL backend against simulated CiA 402 drives, on python-can's virtual bus (and vcan).

Every test gets its own channel name and shuts down every node and bus it started; an autouse
fixture fails any test that leaves a thread behind.
"""

from __future__ import annotations

import dataclasses
import json
import math
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import can
import numpy as np
import pytest
from typer.testing import CliRunner

from core.robot import TwinRobot
from server.hal.base import AXIS_COUNT, DriveState, HalCommand, HalError, HalReading, HalState
from server.hal.canopen import cia402
from server.hal.canopen.master import CanopenHal, create_canopen_hal
from server.hal.canopen.simulated_drive import SimulatedDriveRack
from server.hal.canopen.units import (
    DEFAULT_CONFIGURATION_PATH,
    AxisScaling,
    DriveConfiguration,
    DriveConfigurationError,
    drive_configuration_from_dict,
    load_drive_configuration,
)
from tests.server.canopen_fixtures import (  # noqa: F401 (no_leaked_threads: an autouse fixture)
    brisk_configuration,
    no_leaked_threads,
    wait_until,
)

PERIOD_S = 0.002
HEARTBEAT_TIMEOUT_MS = 500
EDS_DIRECTORY = DEFAULT_CONFIGURATION_PATH.parent / "eds"
VCAN = Path("/sys/class/net/vcan0")


@pytest.fixture
def channel() -> str:
    return f"ssp-test-{uuid.uuid4().hex[:10]}"


@pytest.fixture(scope="module")
def configuration() -> DriveConfiguration:
    return brisk_configuration(HEARTBEAT_TIMEOUT_MS)


@pytest.fixture
def rack(configuration: DriveConfiguration, channel: str) -> Iterator[SimulatedDriveRack]:
    drives = SimulatedDriveRack(configuration, interface="virtual", channel=channel)
    drives.start()
    yield drives
    drives.shutdown()


@pytest.fixture
def hal(
    twin: TwinRobot, configuration: DriveConfiguration, channel: str, rack: SimulatedDriveRack
) -> Iterator[CanopenHal]:
    backend = CanopenHal(twin, PERIOD_S, interface="virtual", channel=channel, configuration=configuration)
    yield backend
    backend.shutdown()


def cycle(hal: CanopenHal, reading: HalReading, command: HalCommand | None = None, wait_s: float = 1.0) -> None:
    """One tick as the worker runs it: write (when active), then read what the drives answered.

    Lock-step (the next SYNC waits for every answer) so each reading belongs to its own cycle.
    """
    if command is not None and hal.state is HalState.ACTIVE:
        hal.write(command)
    hal.wait_for_feedback(wait_s)
    hal.read(reading)


def enable(hal: CanopenHal) -> HalReading:
    hal.configure()
    hal.home()
    hal.activate()
    reading = HalReading()
    hal.read(reading)
    return reading


def move(
    hal: CanopenHal, cycles: int, *, speed_m_s: float = 0.5, at: dict[int, Callable[[], None]] | None = None
) -> HalReading:
    """Drive every axis outwards, ramping up at 20 m/s² to `speed_m_s`; `at[k]()` runs before tick k.

    Stops early once the HAL leaves ACTIVE, as the worker does.
    """
    reading, command = HalReading(), HalCommand()
    hal.read(reading)
    command.positions_m[:] = reading.positions_m
    speed = 0.0
    for k in range(cycles):
        if at and k in at:
            at[k]()
        if hal.state is not HalState.ACTIVE:
            break
        speed = min(speed_m_s, speed + 20.0 * hal.control_period_s)
        command.positions_m += hal.scaling.direction * speed * hal.control_period_s
        cycle(hal, reading, command)
    return reading


def spin(hal: CanopenHal, seconds: float, wait_s: float = 1.0) -> HalReading:
    """Keep reading (SYNC keeps going) for `seconds` of drive time, as a worker does after a fault."""
    reading = HalReading()
    for _ in range(round(seconds / hal.control_period_s)):
        cycle(hal, reading, wait_s=wait_s)
    return reading


def event_kinds(events: list[dict]) -> list[str]:
    return [e["kind"] for e in events]


def assert_controlled_stop(rack: SimulatedDriveRack, configuration: DriveConfiguration) -> None:
    """Every drive at standstill, and no stop harder than its quick-stop deceleration 0x6085."""
    for axis in configuration.axes:
        drive = rack.drive(axis.node_id)
        assert drive.velocity_counts_s == 0.0, f"node {axis.node_id} still moving"
        limit = axis.drive_type.counts(axis.drive_type.quick_stop_deceleration_mm_s2)
        assert drive.trace.peak_stop_deceleration_counts_s2 <= limit * 1.001


# --- configuration and scaling ----------------------------------------------------------------------


def test_scaling_round_trips_counts_and_grows_outwards(twin: TwinRobot) -> None:
    scaling = AxisScaling(load_drive_configuration(), twin)
    positions = scaling.home_position_m + scaling.direction * np.linspace(0.0, 1.6, AXIS_COUNT)
    counts = np.zeros(AXIS_COUNT, dtype=np.int64)
    scaling.counts_from_positions(positions, counts)
    assert np.all(counts >= 0) and counts[-1] == round(1600 * 6553.6)
    back = np.zeros(AXIS_COUNT)
    scaling.positions_from_counts(counts, back)
    assert np.max(np.abs(back - positions)) <= 0.5 / scaling.counts_per_m[0]
    forces = np.zeros(AXIS_COUNT)
    scaling.forces_from_torque(np.full(AXIS_COUNT, 500), forces)
    np.testing.assert_allclose(forces, 2000.0 * scaling.direction)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"direction": 2}, "direction"),
        ({"home_position_mm": 5.0}, "home_position_mm"),
        # Inside the stroke, but no platform pose puts slider 1 there with the others at neutral.
        ({"home_position_mm": 150.0}, r"axes\[0\.\.5\] \(right robot\)\.home_position_mm"),
        ({"node_id": 2}, "axes.node_id"),
        ({"drive_type": "nope"}, "drive_type"),
    ],
)
def test_invalid_drive_configuration_names_the_field(twin: TwinRobot, change: dict, field: str) -> None:
    import tomllib

    data = tomllib.loads(DEFAULT_CONFIGURATION_PATH.read_text())
    data["axes"][0].update(change)
    with pytest.raises(DriveConfigurationError, match=field):
        AxisScaling(drive_configuration_from_dict(data, DEFAULT_CONFIGURATION_PATH.parent), twin)


def test_bus_load_over_the_limit_is_refused_before_the_bus_opens(
    twin: TwinRobot, configuration: DriveConfiguration
) -> None:
    """Twelve axes at 1 kHz cannot fit one 1 Mbit/s CAN bus: 4675 bits per cycle at worst-case stuffing."""
    hal = CanopenHal(twin, 0.001, interface="virtual", channel="unused", configuration=configuration, bitrate=1_000_000)
    with pytest.raises(
        DriveConfigurationError, match=r"control_period_s = 0.001: 12 axes need 4675 bits.*shortest period is 6.68 ms"
    ):
        hal.configure()
    assert hal.network is None and hal.state is HalState.UNCONFIGURED


# --- boot, NMT, PDO mapping, heartbeats ---------------------------------------------------------------


def test_configure_boots_maps_pdos_and_starts_heartbeats(hal: CanopenHal, rack: SimulatedDriveRack) -> None:
    hal.configure()
    reading = HalReading()
    hal.read(reading)
    assert hal.state is HalState.CONFIGURED
    assert np.all(reading.drive_states == DriveState.SWITCH_ON_DISABLED)
    for node_id in hal.node_ids:
        drive = rack.drive(node_id)
        assert drive.node.nmt.state == "OPERATIONAL"
        assert [drive.parameter(0x1600, s) for s in range(4)] == [3, 0x60400010, 0x607A0020, 0x60600008]
        assert [drive.parameter(0x1A00, s) for s in range(4)] == [3, 0x60410010, 0x60640020, 0x60770010]
        assert [drive.parameter(0x1A01, s) for s in range(4)] == [3, 0x606C0020, 0x603F0010, 0x60610008]
        assert drive.parameter(0x1800, 2) == 1 and drive.parameter(0x1006) == 2000
        assert drive.parameter(cia402.CONSUMER_HEARTBEAT_TIME, 1) == 127 << 16 | HEARTBEAT_TIMEOUT_MS
        assert drive.parameter(cia402.QUICK_STOP_OPTION_CODE) == cia402.QuickStopOption.QUICK_STOP_RAMP_AND_STAY
    # Both heartbeat directions are alive: the master hears every drive, every drive hears the master.
    assert wait_until(lambda: bool(np.all(time.monotonic() - hal.heartbeat_seen_s < 0.1)), 2.0)
    assert all(rack.drive(n).master_heartbeat_seen_s is not None for n in hal.node_ids)


def test_missing_drive_fails_configure_naming_it(
    twin: TwinRobot, configuration: DriveConfiguration, channel: str
) -> None:
    hal = create_canopen_hal(twin, PERIOD_S, "virtual", channel, configuration=configuration, simulate=11)
    with pytest.raises(DriveConfigurationError, match=r"left slider 6 \(node 12\).*no boot-up"):
        hal.configure()
    assert hal.state is HalState.UNCONFIGURED and hal.network is None


# --- homing and cyclic synchronous position -----------------------------------------------------------


def run_csp_profile(hal: CanopenHal) -> float:
    """Out and back by 30 mm in 0.4 s; returns the largest following error (m)."""
    reading, command = HalReading(), HalCommand()
    hal.read(reading)
    start = reading.positions_m.copy()
    previous, worst = start.copy(), 0.0
    cycles = 200
    for k in range(1, cycles + 1):
        command.positions_m[:] = start + hal.scaling.direction * 0.03 * (1 - math.cos(2 * math.pi * k / cycles)) / 2
        cycle(hal, reading, command)
        worst = max(worst, float(np.max(np.abs(previous - reading.positions_m))))
        previous[:] = command.positions_m
    return worst


def test_home_then_cyclic_synchronous_position_follows_the_profile(hal: CanopenHal, rack: SimulatedDriveRack) -> None:
    with pytest.raises(HalError, match="not homed"):
        hal.configure()
        hal.activate()
    hal.home()
    reading = HalReading()
    hal.read(reading)
    assert reading.homed.all()
    np.testing.assert_allclose(reading.positions_m, hal.scaling.home_position_m, atol=1e-6)
    # The drive's true carriage stopped on its switch edge, wherever it powered up.
    assert all(abs(rack.drive(n).true_position_counts) < 1.0 for n in hal.node_ids)
    hal.activate()
    assert np.all(hal.mode_display == cia402.OperationMode.CYCLIC_SYNCHRONOUS_POSITION)
    worst_m = run_csp_profile(hal)
    assert worst_m < 1e-4, f"following error {worst_m * 1e3:.3f} mm"
    reading = spin(hal, 0.05)  # the drives answer one SYNC behind and the servo settles: let them
    np.testing.assert_allclose(reading.positions_m, hal.scaling.home_position_m, atol=1e-6)
    hal.deactivate()
    spin(hal, 0.01)
    assert np.all(hal.drive_states == DriveState.SWITCH_ON_DISABLED), hal.drain_events()
    assert not [e for e in hal.drain_events() if e["kind"] not in ("homed",)]


@pytest.mark.skipif(
    not VCAN.exists(), reason="no Linux vcan0 interface on this machine (modprobe vcan; ip link add vcan0 type vcan)"
)
def test_cyclic_synchronous_position_on_linux_vcan(twin: TwinRobot, configuration: DriveConfiguration) -> None:
    hal = create_canopen_hal(twin, PERIOD_S, "socketcan", "vcan0", configuration=configuration, simulate=AXIS_COUNT)
    try:
        enable(hal)
        assert run_csp_profile(hal) < 1e-4
    finally:
        hal.shutdown()


def test_homing_method_is_written_from_configuration(
    twin: TwinRobot, configuration: DriveConfiguration, channel: str, rack: SimulatedDriveRack
) -> None:
    """Method 37 (home on the current position) sets the reference without moving any carriage."""
    hal = CanopenHal(
        twin, PERIOD_S, interface="virtual", channel=channel, configuration=configuration.with_homing_method(37)
    )
    try:
        before = {n: rack.drive(n).true_position_counts for n in hal.node_ids}
        hal.configure()
        hal.home()
        assert all(rack.drive(n).parameter(cia402.HOMING_METHOD) == 37 for n in hal.node_ids)
        assert all(abs(rack.drive(n).true_position_counts - before[n]) <= 0.5 for n in hal.node_ids)  # ≤ ½ count
        reading = spin(hal, 0.004)
        np.testing.assert_allclose(reading.positions_m, hal.scaling.home_position_m, atol=1e-6)
    finally:
        hal.shutdown()


def test_unsupported_homing_method_is_refused_at_configure(
    twin: TwinRobot, configuration: DriveConfiguration, channel: str, rack: SimulatedDriveRack
) -> None:
    hal = CanopenHal(
        twin, PERIOD_S, interface="virtual", channel=channel, configuration=configuration.with_homing_method(99)
    )
    with pytest.raises(DriveConfigurationError, match=r"homing_method = 99.*refused 0x6098"):
        hal.configure()
    assert hal.state is HalState.UNCONFIGURED and hal.network is None


# --- faults -----------------------------------------------------------------------------------------


def test_drive_fault_mid_motion_stops_every_axis_and_is_logged(
    hal: CanopenHal, rack: SimulatedDriveRack, configuration: DriveConfiguration
) -> None:
    enable(hal)
    move(hal, 80, at={40: lambda: rack.drive(3).inject_fault(0x2310)})
    assert hal.state is HalState.FAULT
    assert "right slider 3 (node 3): drive fault 0x2310" in (hal.last_fault or "")
    spin(hal, 0.15)  # the worker keeps reading: SYNC goes on while the drives ramp down
    events = hal.drain_events()
    assert {"drive_emcy", "drive_fault", "quick_stop"} <= set(event_kinds(events))
    fault = next(e for e in events if e["kind"] == "drive_fault")
    assert fault["details"]["node_id"] == 3 and fault["details"]["error_code"] == 0x2310 and fault["utc"]
    assert_controlled_stop(rack, configuration)
    for node_id in hal.node_ids:
        expected = DriveState.FAULT if node_id == 3 else DriveState.QUICK_STOP_ACTIVE
        assert rack.drive(node_id).state == expected
    # Reset: every axis back to SWITCH_ON_DISABLED, power off, nothing moves by itself.
    hal.reset_fault()
    assert hal.state is HalState.CONFIGURED
    assert np.all(spin(hal, 0.01).drive_states == DriveState.SWITCH_ON_DISABLED)


def test_following_error_faults_the_drive_and_stops_every_axis(
    hal: CanopenHal, rack: SimulatedDriveRack, configuration: DriveConfiguration
) -> None:
    enable(hal)
    rack.drive(8).servo.max_acceleration_m_s2 = 0.5  # a jammed axis cannot keep up
    move(hal, 150, speed_m_s=1.2)
    assert hal.state is HalState.FAULT
    assert f"0x{cia402.EMCY_FOLLOWING_ERROR:04X} following error" in (hal.last_fault or "")
    spin(hal, 0.2)  # 1.2 m/s at 10 m/s² stops in 0.12 s
    assert_controlled_stop(rack, configuration)


def test_silent_drive_times_out_and_every_axis_stops(
    hal: CanopenHal, rack: SimulatedDriveRack, configuration: DriveConfiguration
) -> None:
    enable(hal)
    move(hal, 1000, at={30: rack.drive(5).unplug})
    assert hal.state is HalState.FAULT
    assert "right slider 5 (node 5): heartbeat lost" in (hal.last_fault or "")
    spin(hal, 0.15, wait_s=0.005)  # node 5 never answers: do not wait for its TPDOs
    # The unplugged drive lost the master too: it stopped itself on its own clock.
    assert wait_until(lambda: rack.drive(5).state == DriveState.FAULT, 1.0)
    assert rack.drive(5).error_code == cia402.EMCY_HEARTBEAT_LOST
    assert_controlled_stop(rack, configuration)
    assert "heartbeat_lost" in event_kinds(hal.drain_events())
    with pytest.raises(HalError, match=r"no heartbeat from right slider 5"):
        hal.reset_fault()


def test_master_disappearing_makes_every_drive_stop_itself(
    hal: CanopenHal, rack: SimulatedDriveRack, configuration: DriveConfiguration
) -> None:
    enable(hal)
    move(hal, 60, speed_m_s=1.0)
    hal._close()  # the worker process dies: no more SYNC, RPDO or heartbeat from the master
    assert wait_until(lambda: all(rack.drive(n).state == DriveState.FAULT for n in hal.node_ids), 2.0)
    for node_id in hal.node_ids:
        assert rack.drive(node_id).error_code == cia402.EMCY_HEARTBEAT_LOST
        assert cia402.EMCY_HEARTBEAT_LOST in rack.drive(node_id).trace.emergencies
        assert DriveState.FAULT_REACTION_ACTIVE in rack.drive(node_id).trace.states_seen
    assert_controlled_stop(rack, configuration)


def test_bus_off_stops_safely_with_a_clear_event_and_recovers_on_reset(
    hal: CanopenHal, rack: SimulatedDriveRack, configuration: DriveConfiguration
) -> None:
    enable(hal)
    move(hal, 60, at={30: rack.inject_bus_off})
    assert hal.state is HalState.FAULT
    bus_off = next(e for e in hal.drain_events() if e["kind"] == "bus_off")
    assert f"CAN bus-off on virtual:{hal.channel}" in bus_off["message"]
    assert (
        f"drives stop themselves when the master heartbeat times out ({HEARTBEAT_TIMEOUT_MS} ms)" in bus_off["message"]
    )
    # The master no longer transmits, so every drive's heartbeat consumer stops it.
    assert wait_until(lambda: all(rack.drive(n).state == DriveState.FAULT for n in hal.node_ids), 2.0)
    assert_controlled_stop(rack, configuration)
    hal.reset_fault()
    assert hal.state is HalState.CONFIGURED
    assert {"bus_recovered", "fault_reset"} <= set(event_kinds(hal.drain_events()))
    assert np.all(spin(hal, 0.01).drive_states == DriveState.SWITCH_ON_DISABLED)


def test_transmit_failure_faults_the_hal(hal: CanopenHal, monkeypatch: pytest.MonkeyPatch) -> None:
    hal.configure()
    assert hal.network is not None

    def refuse(*args: object, **kwargs: object) -> None:
        raise can.CanOperationError("Transmit buffer full")

    monkeypatch.setattr(hal.network, "send_message", refuse)
    hal.read(HalReading())
    assert hal.state is HalState.FAULT
    assert "bus error: Transmit buffer full" in (hal.last_fault or "")


def test_emergency_stop_ramps_down_then_removes_power(
    hal: CanopenHal, rack: SimulatedDriveRack, configuration: DriveConfiguration
) -> None:
    enable(hal)
    move(hal, 80, speed_m_s=1.0)
    hal.emergency_stop()
    assert hal.state is HalState.ESTOP
    assert_controlled_stop(rack, configuration)
    for node_id in hal.node_ids:
        trace = [to for _, _, to, _ in rack.drive(node_id).trace.transitions]
        assert trace[-2:] == [DriveState.QUICK_STOP_ACTIVE, DriveState.SWITCH_ON_DISABLED]
    hal.reset_estop()
    assert hal.state is HalState.CONFIGURED and np.all(hal.drive_states == DriveState.SWITCH_ON_DISABLED)


def broken_eds(tmp_path: Path, missing_index: int) -> Path:
    """The shipped EDS without one object: what a wrong or truncated vendor file looks like."""
    text = (EDS_DIRECTORY / "ssp_linear_axis.eds").read_text()
    sections = text.split("\n[")
    kept = [s for s in sections if not s.startswith(f"{missing_index:04X}")]
    path = tmp_path / "truncated.eds"
    path.write_text("\n[".join(kept).replace(f"=0x{missing_index:04X}\n", "=0x1000\n"))
    return path


def test_eds_without_a_required_object_is_refused_before_the_bus(
    twin: TwinRobot, configuration: DriveConfiguration, tmp_path: Path
) -> None:
    drive_type = dataclasses.replace(configuration.axes[0].drive_type, eds_path=broken_eds(tmp_path, 0x607A))
    axes = tuple(dataclasses.replace(a, drive_type=drive_type) for a in configuration.axes)
    hal = CanopenHal(
        twin,
        PERIOD_S,
        interface="virtual",
        channel="unused",
        configuration=dataclasses.replace(configuration, axes=axes),
    )
    with pytest.raises(DriveConfigurationError, match=r"drive_types\.ssp-linear-axis\.eds.*0x607A"):
        hal.configure()
    assert hal.network is None


@pytest.mark.parametrize(
    ("wrong", "message"),
    [
        ("eds", r"right slider 4 \(node 4\) reports product code 0x00000301.*wrong EDS"),
        ("modes", r"left slider 1 \(node 7\) 0x6502.*mode 8 \(cyclic synchronous position\) is required"),
    ],
)
def test_wrong_eds_or_unsupported_mode_fails_configure_and_nothing_ever_moves(
    twin: TwinRobot, configuration: DriveConfiguration, channel: str, wrong: str, message: str
) -> None:
    overrides = {4: EDS_DIRECTORY / "generic_pp_servo.eds"} if wrong == "eds" else {}
    rack = SimulatedDriveRack(configuration, interface="virtual", channel=channel, eds_overrides=overrides)
    rack.start()
    if wrong == "modes":
        rack.drive(7).override(cia402.SUPPORTED_DRIVE_MODES, 0, 0x25)  # pp, pv, homing: no CSP
    hal = CanopenHal(twin, PERIOD_S, interface="virtual", channel=channel, configuration=configuration)
    try:
        before = {n: rack.drive(n).true_position_counts for n in rack.node_ids}
        with pytest.raises(DriveConfigurationError, match=message):
            hal.configure()
        assert hal.state is HalState.UNCONFIGURED and hal.network is None
        with pytest.raises(HalError, match="must be configured"):
            hal.activate()
        with pytest.raises(HalError):
            hal.home()
        time.sleep(0.05)
        for node_id in rack.node_ids:
            drive = rack.drive(node_id)
            assert drive.node.nmt.state != "OPERATIONAL"  # no PDO is ever processed
            assert drive.trace.states_seen == {DriveState.SWITCH_ON_DISABLED}
            assert drive.true_position_counts == before[node_id]
    finally:
        hal.shutdown()
        rack.shutdown()


# --- the demo command -----------------------------------------------------------------------------


def relaxed_drives_file(tmp_path: Path) -> Path:
    """The shipped drives.toml with the test heartbeat timeout and absolute EDS paths."""
    text = DEFAULT_CONFIGURATION_PATH.read_text()
    text = text.replace('eds = "eds/', f'eds = "{EDS_DIRECTORY}/')
    text = text.replace("heartbeat_timeout_ms = 200", f"heartbeat_timeout_ms = {HEARTBEAT_TIMEOUT_MS}")
    path = tmp_path / "drives.toml"
    path.write_text(text)
    return path


def test_drives_demo_enables_homes_moves_and_reports_json(channel: str, tmp_path: Path) -> None:
    from server.cli.main import app

    result = CliRunner().invoke(
        app,
        [
            *("drives", "--bus", "virtual", "--channel", channel, "--simulate", "12"),
            *("--drives", str(relaxed_drives_file(tmp_path))),
            *("--period-ms", "2", "--duration-s", "0.3", "--json"),
        ],
    )
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert len(data["axes"]) == AXIS_COUNT
    assert all(a["homed"] and a["final_state"] == "SWITCH_ON_DISABLED" for a in data["axes"])
    assert 0.0 <= data["max_following_error_mm"] < 0.1
    assert data["cycles"] > data["profile_cycles"] == 150
    reached = {(t["from"], t["to"]) for t in data["transitions"]}
    assert ("SWITCHED_ON", "OPERATION_ENABLED") in reached and ("OPERATION_ENABLED", "SWITCH_ON_DISABLED") in reached


def test_drives_demo_without_drives_fails_clearly(channel: str) -> None:
    from server.cli.main import app

    result = CliRunner().invoke(app, ["drives", "--bus", "virtual", "--channel", channel, "--simulate", "0", "--json"])
    assert result.exit_code == 2
    assert "no boot-up" in json.loads(result.stdout)["error"]
