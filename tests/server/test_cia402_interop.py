"""CiA 402 interoperability, both ways, on python-can's virtual bus.

1. python-canopen's own `BaseNode402`, a master independent of this product, enables the product's
   simulated drive and moves it: by SDO alone, and by event-driven PDOs (transmission type 255, no SYNC).
2. The product's master (`CanopenHal`) commissions, homes, enables, faults, resets and emergency-stops
   drives written here from the CiA 402 standard on python-canopen's `LocalNode`, without the product's
   `cia402` table or its simulated drive.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator

import canopen
import pytest
from canopen.profiles.p402 import BaseNode402

from server.hal.base import DriveState
from server.hal.canopen.simulated_drive import SimulatedDriveRack
from server.hal.canopen.units import DEFAULT_CONFIGURATION_PATH, DriveConfiguration, load_drive_configuration

EDS = DEFAULT_CONFIGURATION_PATH.parent / "eds" / "ssp_linear_axis.eds"
NODE_ID = 1
STEP_COUNTS = 13_107  # 2 mm at 6553.6 counts/mm: well inside the drive's default following-error window (5 mm)
EVENT_TIMER_MS = 20  # TPDOs on change, and at least this often (BaseNode402 waits 0.2 s for a statusword)


def wait_until(predicate: Callable[[], bool], timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        leaked = [t for t in set(threading.enumerate()) - before if t.is_alive()]
        if not leaked:
            return
        time.sleep(0.02)
    pytest.fail(f"threads left running: {leaked}")


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
