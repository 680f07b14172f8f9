"""CiA 402 interoperability, both ways, on python-can's virtual bus.

1. python-canopen's own `BaseNode402`, a master independent of this product, enables the product's
   simulated drive and moves it: by SDO alone, and by event-driven PDOs (transmission type 255, no SYNC).
2. The product's master (`CanopenHal`) commissions, homes, enables, faults, resets and emergency-stops
   drives written here from the CiA 402 standard on python-canopen's `LocalNode`, without the product's
   `cia402` table or its simulated drive.
"""

from __future__ import annotations

import dataclasses
import threading
import time
import uuid
from collections.abc import Iterator

import canopen
import numpy as np
import pytest
from canopen.profiles.p402 import BaseNode402

from core.robot import TwinRobot
from server.hal.base import DriveState, HalCommand, HalReading, HalState
from server.hal.canopen.master import CanopenHal
from server.hal.canopen.simulated_drive import SimulatedDriveRack
from server.hal.canopen.units import DEFAULT_CONFIGURATION_PATH, DriveConfiguration, load_drive_configuration
from tests.server.canopen_fixtures import no_leaked_threads  # noqa: F401 (autouse fixture)
from tests.server.test_hal_canopen import wait_until

EDS = DEFAULT_CONFIGURATION_PATH.parent / "eds" / "ssp_linear_axis.eds"
NODE_ID = 1
STEP_COUNTS = 13_107  # 2 mm at 6553.6 counts/mm: well inside the drive's default following-error window (5 mm)
EVENT_TIMER_MS = 20  # TPDOs on change, and at least this often (BaseNode402 waits 0.2 s for a statusword)


@pytest.fixture
def channel() -> str:
    return f"ssp-interop-{uuid.uuid4().hex[:10]}"


@pytest.fixture
def configuration() -> DriveConfiguration:
    return load_drive_configuration()


# --- 1. an independent master (python-canopen's BaseNode402) on the product's simulated drive ----------


@pytest.fixture
def simulated_drive(configuration: DriveConfiguration, channel: str) -> Iterator[SimulatedDriveRack]:
    rack = SimulatedDriveRack(configuration, interface="virtual", channel=channel, node_ids=[NODE_ID])
    rack.start()
    yield rack
    rack.shutdown()


@pytest.fixture
def base_node(simulated_drive: SimulatedDriveRack, channel: str) -> Iterator[BaseNode402]:
    network = canopen.Network()
    network.NOTIFIER_CYCLE = 0.05
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    node = BaseNode402(NODE_ID, str(EDS))
    network.add_node(node)
    # Generous waits for a loaded test machine; BaseNode402's defaults assume a quiet bus and host.
    node.sdo.RESPONSE_TIMEOUT = 1.0
    node.TIMEOUT_SWITCH_STATE_FINAL = node.TIMEOUT_SWITCH_STATE_SINGLE = 3.0
    node.TIMEOUT_SWITCH_OP_MODE = 3.0
    yield node
    network.disconnect()


def test_base_node_402_enables_and_moves_the_simulated_drive_by_sdo(
    base_node: BaseNode402, simulated_drive: SimulatedDriveRack
) -> None:
    """Defect (issue 12 §6): `node.state = 'OPERATION ENABLED'` timed out with the statusword at 0x0240."""
    node = base_node
    node.nmt.state = "OPERATIONAL"
    node.state = "OPERATION ENABLED"  # controlwords by SDO 0x6040, statusword read back by SDO 0x6041
    assert node.state == "OPERATION ENABLED"
    node.op_mode = "CYCLIC SYNCHRONOUS POSITION"  # SDO 0x6060; BaseNode402 waits for 0x6061 to follow
    assert node.sdo[0x6061].raw == 8, "0x6061 must show the mode in effect"
    start = node.sdo[0x6064].raw
    for step in (1, 2, 3):
        target = start + step * STEP_COUNTS
        node.sdo[0x607A].raw = target
        assert wait_until(lambda t=target: abs(node.sdo[0x6064].raw - t) <= 10, 5.0), (
            f"position actual {node.sdo[0x6064].raw} never reached target {target}"
        )
    assert simulated_drive.drive(NODE_ID).state == DriveState.OPERATION_ENABLED  # no fault on the way
    node.state = "SWITCH ON DISABLED"
    assert node.state == "SWITCH ON DISABLED"


def test_simulated_drive_refuses_a_mode_it_does_not_implement(base_node: BaseNode402) -> None:
    """A mode write the drive cannot act on is refused (SDO abort), never stored as if it had taken."""
    with pytest.raises(canopen.SdoAbortedError):
        base_node.sdo[0x6060].raw = 1  # profile position: the simulated drive implements CSP and homing
    assert base_node.sdo[0x6061].raw == 0


def _map_event_driven_pdos(node: BaseNode402) -> None:
    """RPDO1 controlword/target/mode and TPDO1 statusword/position, TPDO2 mode display/velocity, all
    transmission type 255 (event-driven): no SYNC anywhere on the bus."""
    node.rpdo.read()
    node.tpdo.read()
    layout = [
        (node.rpdo, [(0x6040, 0x607A, 0x6060)]),
        (node.tpdo, [(0x6041, 0x6064), (0x6061, 0x606C)]),
    ]
    for maps, pdos in layout:
        for number, pdo in maps.map.items():
            pdo.clear()
            indices = pdos[number - 1] if number <= len(pdos) else ()
            for index in indices:
                pdo.add_variable(index)
            pdo.trans_type = 255
            if maps is node.tpdo:
                pdo.event_timer = EVENT_TIMER_MS
            pdo.enabled = bool(indices)
        maps.save()
    node.setup_402_state_machine(read_pdos=False)


def test_base_node_402_enables_and_moves_the_simulated_drive_by_event_driven_pdo(
    base_node: BaseNode402, simulated_drive: SimulatedDriveRack
) -> None:
    node = base_node
    _map_event_driven_pdos(node)
    node.nmt.state = "OPERATIONAL"
    assert wait_until(lambda: 0x6041 in node.tpdo_values and node.tpdo_values[0x6041] != 0, 2.0), (
        "no event-driven TPDO with the statusword"
    )
    node.rpdo_pointers[0x607A].raw = node.tpdo_values[0x6064]  # hold where it stands
    node.op_mode = "CYCLIC SYNCHRONOUS POSITION"  # by RPDO now, confirmed from the TPDO
    assert node.op_mode == "CYCLIC SYNCHRONOUS POSITION"
    node.state = "OPERATION ENABLED"
    assert node.state == "OPERATION ENABLED"
    start = node.tpdo_values[0x6064]
    for step in (1, 2, 3):
        target = start + step * STEP_COUNTS
        node.rpdo_pointers[0x607A].raw = target
        node.rpdo[1].transmit()
        assert wait_until(lambda t=target: abs(node.tpdo_values[0x6064] - t) <= 10, 5.0), (
            f"position actual {node.tpdo_values[0x6064]} never reached target {target}"
        )
    assert simulated_drive.drive(NODE_ID).state == DriveState.OPERATION_ENABLED
    node.state = "SWITCH ON DISABLED"
    assert node.state == "SWITCH ON DISABLED"


# --- 2. the product's master on drives written here from the CiA 402 standard --------------------------

# Statusword state codes, CiA 402 §6.2.2 table 30 (value with bits 0–3, 5, 6).
STATUSWORD = {
    "SWITCH ON DISABLED": 0x0040,
    "READY TO SWITCH ON": 0x0021,
    "SWITCHED ON": 0x0023,
    "OPERATION ENABLED": 0x0027,
    "QUICK STOP ACTIVE": 0x0007,
    "FAULT REACTION ACTIVE": 0x000F,
    "FAULT": 0x0008,
}
HOMING_MODE, CSP_MODE = 6, 8


def device_command(controlword: int) -> str | None:
    """Decode a controlword's device-control command, CiA 402 §6.2.1 table 28 (fault reset aside)."""
    if controlword & 0x0082 == 0x0000:
        return "disable voltage"
    if controlword & 0x0086 == 0x0002:
        return "quick stop"
    if controlword & 0x0087 == 0x0006:
        return "shutdown"
    if controlword & 0x008F == 0x0007:
        return "switch on"  # also "disable operation"
    if controlword & 0x008F == 0x000F:
        return "enable operation"  # also "switch on + enable operation"
    return None


# (state, command) → next state, CiA 402 §6.2 figure 31; "switch on + enable operation" takes 3 then 4.
NEXT_STATE = {
    ("SWITCH ON DISABLED", "shutdown"): "READY TO SWITCH ON",  # 2
    ("READY TO SWITCH ON", "switch on"): "SWITCHED ON",  # 3
    ("READY TO SWITCH ON", "enable operation"): "OPERATION ENABLED",  # 3 + 4
    ("READY TO SWITCH ON", "disable voltage"): "SWITCH ON DISABLED",  # 7
    ("READY TO SWITCH ON", "quick stop"): "SWITCH ON DISABLED",  # 7
    ("SWITCHED ON", "enable operation"): "OPERATION ENABLED",  # 4
    ("SWITCHED ON", "shutdown"): "READY TO SWITCH ON",  # 6
    ("SWITCHED ON", "disable voltage"): "SWITCH ON DISABLED",  # 10
    ("SWITCHED ON", "quick stop"): "SWITCH ON DISABLED",  # 10
    ("OPERATION ENABLED", "switch on"): "SWITCHED ON",  # 5
    ("OPERATION ENABLED", "shutdown"): "READY TO SWITCH ON",  # 8
    ("OPERATION ENABLED", "disable voltage"): "SWITCH ON DISABLED",  # 9
    ("OPERATION ENABLED", "quick stop"): "QUICK STOP ACTIVE",  # 11
    ("QUICK STOP ACTIVE", "disable voltage"): "SWITCH ON DISABLED",  # 12
}


class StandardDrive:
    """An ideal CiA 402 position drive on a LocalNode: CSP (the axis is where the last target put it), homing
    on the current position (methods 35/37), quick stop per 0x605A, faults with EMCY and fault reset."""

    def __init__(self, network: canopen.Network, node_id: int) -> None:
        self.node = canopen.LocalNode(node_id, str(EDS))
        network.add_node(self.node)
        self.node.add_read_callback(self._on_read)
        self.state = "SWITCH ON DISABLED"
        self.states_seen = {self.state}
        self.controlword = 0
        self.mode_display = 0
        self.position = 0  # encoder counts; the drive powers up wherever it stands
        self.home_reference = 0
        self.velocity = 0
        self.homed = False
        self.error_code = 0
        self.pending_fault: int | None = None

    def parameter(self, index: int) -> int:
        return int(self.node.sdo[index].raw)

    def _on_read(self, index: int, subindex: int, od: object) -> int | None:
        live = {0x6041: self.statusword(), 0x6064: self.position - self.home_reference, 0x6061: self.mode_display}
        return live.get(index)

    def statusword(self) -> int:
        word = STATUSWORD[self.state] | 0x0200  # remote
        if self.mode_display == HOMING_MODE and self.homed:
            word |= 0x1000 | 0x0400  # homing attained, target reached
        return word

    def boot(self) -> None:
        self.node.nmt.send_command(0x81)  # INITIALISING: the boot-up message
        self.node.nmt.send_command(0x80)  # PRE-OPERATIONAL, heartbeat from 0x1017

    def start(self) -> None:
        """NMT start: take the PDO mapping the master wrote."""
        self.node.rpdo.read()
        self.node.tpdo.read()

    def on_sync(self, period_s: float) -> None:
        if self.node.nmt.state != "OPERATIONAL":
            return
        received = {var.index: var.raw for pdo in self.node.rpdo.map.values() if pdo.enabled for var in pdo.map}
        if self.pending_fault is not None:
            self.error_code, self.pending_fault = self.pending_fault, None
            self.node.emcy.send(self.error_code, 1)
            self._enter("FAULT REACTION ACTIVE")
            self.velocity = 0  # an ideal drive is at standstill at once
            self._enter("FAULT")
        if 0x6060 in received and received[0x6060] in (HOMING_MODE, CSP_MODE):
            self.mode_display = int(received[0x6060])
        if 0x6040 in received:
            self._controlword(int(received[0x6040]))
        previous = self.position
        if self.state == "OPERATION ENABLED" and self.mode_display == CSP_MODE and 0x607A in received:
            self.position = int(received[0x607A]) + self.home_reference
        self.velocity = round((self.position - previous) / period_s) if period_s else 0
        live = {
            0x6041: self.statusword(),
            0x6064: self.position - self.home_reference,
            0x6077: 0,
            0x606C: self.velocity,
            0x603F: self.error_code,
            0x6061: self.mode_display,
        }
        for pdo in self.node.tpdo.map.values():
            if pdo.enabled and pdo.map:
                for var in pdo.map:
                    var.raw = live[var.index]
                pdo.transmit()

    def _controlword(self, word: int) -> None:
        previous, self.controlword = self.controlword, word
        if self.state == "FAULT":
            if word & 0x0080 and not previous & 0x0080:  # fault reset on the rising edge (15)
                self.error_code = 0
                self._enter("SWITCH ON DISABLED")
            return
        command = device_command(word)
        if self.state == "QUICK STOP ACTIVE" and command == "enable operation":
            if self.parameter(0x605A) in (5, 6, 7, 8):  # 16 only under a "stay" option
                self._enter("OPERATION ENABLED")
            return
        next_state = NEXT_STATE.get((self.state, command or ""))
        if next_state == "QUICK STOP ACTIVE" and self.parameter(0x605A) in (0, 1, 2, 3, 4):
            next_state = "SWITCH ON DISABLED"  # stopped at once, then disabled (12)
        if next_state is not None:
            self._enter(next_state)
        homing = self.state == "OPERATION ENABLED" and self.mode_display == HOMING_MODE
        if homing and word & 0x0010 and not previous & 0x0010 and self.parameter(0x6098) in (35, 37):
            self.home_reference = self.position - self.parameter(0x607C)
            self.homed = True

    def _enter(self, state: str) -> None:
        self.state = state
        self.states_seen.add(state)


class StandardDriveRack:
    """Standard drives for `node_ids` on one connection, answering NMT and SYNC."""

    def __init__(self, channel: str, node_ids: list[int]) -> None:
        self.network = canopen.Network()
        self.network.NOTIFIER_CYCLE = 0.05
        self.drives = {node_id: StandardDrive(self.network, node_id) for node_id in node_ids}
        self.network.subscribe(0x80, self._on_sync)
        self.network.subscribe(0, self._on_nmt)
        self.network.connect(interface="virtual", channel=channel, receive_own_messages=False)
        self.lock = threading.Lock()
        for drive in self.drives.values():
            drive.boot()

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        command, node_id = data[0], data[1]
        with self.lock:
            for drive in self.drives.values():
                if node_id in (0, drive.node.id):
                    if command in (0x81, 0x82):
                        drive.boot()
                    elif command == 0x01:
                        drive.start()

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        with self.lock:
            for drive in self.drives.values():
                drive.on_sync(drive.parameter(0x1006) / 1e6)

    def close(self) -> None:
        for drive in self.drives.values():
            drive.node.nmt.stop_heartbeat()
        self.network.disconnect()


def test_product_master_runs_drives_written_from_the_standard(
    twin: TwinRobot, channel: str, configuration: DriveConfiguration
) -> None:
    configuration = dataclasses.replace(configuration.with_homing_method(35), heartbeat_timeout_ms=500)
    rack = StandardDriveRack(channel, configuration.node_ids)
    hal = CanopenHal(twin, 0.002, interface="virtual", channel=channel, configuration=configuration)
    drives = list(rack.drives.values())
    reading = HalReading()

    def tick(command: HalCommand | None = None) -> None:
        if command is not None:
            hal.write(command)
        hal.wait_for_feedback(1.0)
        hal.read(reading)

    try:
        hal.configure()  # commissioning: identity, parameters and PDO mapping by SDO, NMT start
        assert all(d.node.nmt.state == "OPERATIONAL" and d.parameter(0x6098) == 35 for d in drives)
        assert all(d.parameter(0x605A) == 6 and d.node.tpdo.map[1].enabled for d in drives)
        hal.home()
        tick()
        assert reading.homed.all() and all(d.homed for d in drives)
        hal.activate()
        tick()
        assert all(d.state == "OPERATION ENABLED" and d.mode_display == CSP_MODE for d in drives)
        command = HalCommand()
        command.positions_m[:] = reading.positions_m
        for _ in range(50):  # outwards at 0.1 m/s: the ideal drives follow the set-points exactly
            command.positions_m += hal.scaling.direction * 0.1 * hal.control_period_s
            tick(command)
        tick(command)
        np.testing.assert_allclose(reading.positions_m, command.positions_m, atol=1e-6)

        drives[2].pending_fault = 0x2310  # over-current on node 3
        for _ in range(20):
            if hal.state is not HalState.ACTIVE:
                break
            tick(command)
        assert hal.state is HalState.FAULT
        assert "node 3" in (hal.last_fault or "") and "0x2310" in (hal.last_fault or "")
        tick()  # the quick-stop cycle's answers
        assert drives[2].state == "FAULT"
        assert all(d.state == "QUICK STOP ACTIVE" for i, d in enumerate(drives) if i != 2)
        hal.reset_fault()
        assert hal.state is HalState.CONFIGURED
        assert all(d.state == "SWITCH ON DISABLED" and d.error_code == 0 for d in drives)

        hal.activate()
        tick()
        hal.emergency_stop()
        assert hal.state is HalState.ESTOP
        assert all(d.state == "SWITCH ON DISABLED" and "QUICK STOP ACTIVE" in d.states_seen for d in drives)
        hal.reset_estop()
        for _ in range(20):
            tick()
        assert hal.state is HalState.CONFIGURED
        assert all(d.state == "SWITCH ON DISABLED" for d in drives)  # a reset never re-enables
    finally:
        hal.shutdown()
        rack.close()


def test_quick_stop_of_the_simulated_drive_follows_its_option_code(
    base_node: BaseNode402, simulated_drive: SimulatedDriveRack
) -> None:
    """0x605A = 2: after the ramp the drive disables itself (12). 0x605A = 6: it stays in QUICK STOP ACTIVE,
    holding, and only then does "enable operation" take it back (16)."""
    node = base_node
    node.nmt.state = "OPERATIONAL"
    node.sdo[0x605A].raw = 2
    node.state = "OPERATION ENABLED"
    node.controlword = 0x0002  # quick stop
    assert wait_until(lambda: node.state == "SWITCH ON DISABLED", 3.0), node.state
    reasons = [reason for *_, reason in simulated_drive.drive(NODE_ID).trace.transitions]
    assert reasons[-2:] == ["quick stop", "quick stop done"]
    node.sdo[0x605A].raw = 6
    node.state = "OPERATION ENABLED"
    node.controlword = 0x0002
    assert wait_until(lambda: node.state == "QUICK STOP ACTIVE", 3.0), node.state
    time.sleep(0.1)  # well past the ramp of a drive at standstill
    assert node.state == "QUICK STOP ACTIVE"
    node.controlword = 0x000F  # enable operation: transition 16
    assert wait_until(lambda: node.state == "OPERATION ENABLED", 3.0), node.state
