"""The CiA 402 transition table, shared by the master (path search) and the simulated drive (decode)."""

from __future__ import annotations

import itertools

import canopen
import numpy as np
import pytest

from server.hal.base import DriveState
from server.hal.canopen import cia402
from server.hal.canopen.pdo import PdoCodec, cycle_bus_bits, frame_bits
from server.hal.canopen.units import DEFAULT_CONFIGURATION_PATH

COMMANDED = [t for t in cia402.TRANSITIONS if t.controlword is not None]
REACHABLE_TARGETS = [
    DriveState.SWITCH_ON_DISABLED,
    DriveState.READY_TO_SWITCH_ON,
    DriveState.SWITCHED_ON,
    DriveState.OPERATION_ENABLED,
    DriveState.QUICK_STOP_ACTIVE,
]


def test_enable_path_is_shutdown_switch_on_enable_operation() -> None:
    path = cia402.transition_path(DriveState.SWITCH_ON_DISABLED, DriveState.OPERATION_ENABLED)
    assert [t.number for t in path] == [2, 3, 4]
    assert [t.controlword for t in path] == [0x06, 0x07, 0x0F]


def test_shortest_paths_out_of_operation_and_fault() -> None:
    assert [t.number for t in cia402.transition_path(DriveState.OPERATION_ENABLED, DriveState.SWITCH_ON_DISABLED)] == [
        9
    ]
    assert [t.number for t in cia402.transition_path(DriveState.OPERATION_ENABLED, DriveState.QUICK_STOP_ACTIVE)] == [
        11
    ]
    assert [t.number for t in cia402.transition_path(DriveState.FAULT, DriveState.OPERATION_ENABLED)] == [15, 2, 3, 4]


def test_no_commanded_path_into_fault() -> None:
    with pytest.raises(ValueError, match="FAULT"):
        cia402.transition_path(DriveState.OPERATION_ENABLED, DriveState.FAULT)


@pytest.mark.parametrize("transition", COMMANDED, ids=lambda t: f"t{t.number}")
def test_drive_decodes_every_master_controlword_into_the_same_transition(transition: cia402.Transition) -> None:
    assert transition.controlword is not None
    decoded = cia402.commanded_transition(transition.source, transition.controlword, previous_controlword=0)
    assert decoded == transition


@pytest.mark.parametrize("state", list(DriveState))
def test_hold_controlword_keeps_every_state(state: DriveState) -> None:
    hold = cia402.HOLD_CONTROLWORD[state]
    assert cia402.commanded_transition(state, hold, previous_controlword=hold) is None


def test_fault_reset_acts_only_on_a_rising_edge() -> None:
    assert cia402.commanded_transition(DriveState.FAULT, 0x80, previous_controlword=0x80) is None
    reset = cia402.commanded_transition(DriveState.FAULT, 0x80, previous_controlword=0x00)
    assert reset is not None and reset.number == 15
    # A reset that did not take: the master drops bit 7 for a cycle to make a new edge.
    assert cia402.next_controlword(DriveState.FAULT, DriveState.SWITCH_ON_DISABLED, previous_controlword=0x80) == 0
    assert cia402.next_controlword(DriveState.FAULT, DriveState.SWITCH_ON_DISABLED, previous_controlword=0) == 0x80


@pytest.mark.parametrize(
    ("source", "target"), [(s, t) for s, t in itertools.product(list(DriveState)[1:], REACHABLE_TARGETS)]
)
def test_master_and_drive_running_the_same_table_reach_every_target(source: DriveState, target: DriveState) -> None:
    if source == DriveState.FAULT_REACTION_ACTIVE:
        return  # only the drive leaves it, at the end of its ramp
    try:
        expected_steps = len(cia402.transition_path(source, target))
    except ValueError:
        assert target == DriveState.QUICK_STOP_ACTIVE  # quick stop is entered only from OPERATION_ENABLED
        return
    state: DriveState = source
    previous = 0
    for _ in range(expected_steps):
        word = cia402.next_controlword(state, target, previous)
        taken = cia402.commanded_transition(state, word, previous)
        assert taken is not None
        state, previous = taken.target, word
    assert state == target


def test_statusword_decoding_ignores_bits_outside_the_state_code_and_vector_matches_scalar() -> None:
    for state, extra in itertools.product(
        cia402.STATUSWORD_CODES, [0x0010, 0x0080, 0x0200, 0x0400, 0x1000, 0x2000, 0xB690]
    ):
        assert cia402.state_from_statusword(cia402.statusword_for(state) | extra) == state
    words = np.arange(0, 0x10000, 7, dtype=np.int64)
    decoded = np.zeros(words.size, dtype=np.int8)
    cia402.states_from_statuswords(words, decoded)
    assert decoded.tolist() == [cia402.state_from_statusword(int(w)) for w in words]


def test_pdo_codec_round_trip_and_frame_limit() -> None:
    od = canopen.import_od(str(DEFAULT_CONFIGURATION_PATH.parent / "eds" / "ssp_linear_axis.eds"))
    codec = PdoCodec.from_mapping(0x201, [(0x6040, 16), (0x607A, 32), (0x6060, 8)], od)
    assert codec.unpack(codec.pack([0x1F, -123456, 8])) == (0x1F, -123456, 8)
    with pytest.raises(ValueError, match="exceed"):
        PdoCodec.from_mapping(0x181, [(0x6064, 32), (0x606C, 32), (0x6041, 16)], od)
    with pytest.raises(ValueError, match="mapped with 8 bits"):
        PdoCodec.from_mapping(0x181, [(0x6064, 8)], od)
    # Worst-case stuffed frame lengths: 8 data bytes → 135 bits, SYNC (no data) → 55 bits.
    assert frame_bits(8) == 135 and frame_bits(0) == 55
    assert cycle_bus_bits(12, od) == 55 + 12 * (frame_bits(7) + frame_bits(8) + frame_bits(7))


@pytest.mark.parametrize(
    ("source", "number"), [(DriveState.READY_TO_SWITCH_ON, 7), (DriveState.SWITCHED_ON, 10)], ids=["t7", "t10"]
)
def test_quick_stop_command_disables_voltage_before_operation_is_enabled(source: DriveState, number: int) -> None:
    """CiA 402 §6.2: transitions 7 and 10 are taken on "quick stop" (0x02) as well as on "disable voltage"."""
    taken = cia402.commanded_transition(source, 0x0002, previous_controlword=cia402.HOLD_CONTROLWORD[source])
    assert taken is not None, f"{source.name} ignored the quick stop command 0x0002"
    assert (taken.number, taken.target) == (number, DriveState.SWITCH_ON_DISABLED)


@pytest.mark.parametrize("option", range(9))
def test_enable_operation_leaves_quick_stop_only_under_a_stay_option(option: int) -> None:
    """Transition 16 exists only when 0x605A is 5–8 (stop, then stay in QUICK STOP ACTIVE)."""
    taken = cia402.commanded_transition(
        DriveState.QUICK_STOP_ACTIVE, 0x000F, previous_controlword=0x0002, quick_stop_option=option
    )
    if option in (5, 6, 7, 8):
        assert taken is not None and taken.number == 16
    else:
        assert taken is None
    completion = cia402.quick_stop_completion(option)
    if option in (5, 6, 7, 8):
        assert completion is None  # stays, holding
    else:
        assert completion is not None and (completion.number, completion.target) == (12, DriveState.SWITCH_ON_DISABLED)
