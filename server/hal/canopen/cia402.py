"""The CiA 402 (IEC 61800-7-201) drive profile: power state machine, controlwords and statuswords.

The state machine is one transition table, (state, target) → controlword, after `being/can/cia_402.py`.
The master finds its way between any two states with a breadth-first search over that table; the
simulated drives run the same table backwards, decoding a received controlword into the transition it
commands. Every simulated drive follows this one table: the simulated CANopen drive, the MuJoCo servo
drives and the kinematic backend's ideal drives (`DriveStateMachines`). States are
`server.hal.base.DriveState`, so the HAL reports exactly what the drives report.
"""

from __future__ import annotations

import enum
from collections import deque
from dataclasses import dataclass
from functools import cache

import numpy as np

from server.hal.base import DriveState

# --- Object dictionary indices of the profile (CiA 402 §6) ----------------------------------------

ERROR_CODE = 0x603F
ABORT_CONNECTION_OPTION_CODE = 0x6007
CONTROLWORD = 0x6040
STATUSWORD = 0x6041
QUICK_STOP_OPTION_CODE = 0x605A
FAULT_REACTION_OPTION_CODE = 0x605E
MODES_OF_OPERATION = 0x6060
MODES_OF_OPERATION_DISPLAY = 0x6061
POSITION_ACTUAL = 0x6064
FOLLOWING_ERROR_WINDOW = 0x6065
FOLLOWING_ERROR_TIMEOUT = 0x6066
VELOCITY_ACTUAL = 0x606C
TORQUE_ACTUAL = 0x6077
TARGET_POSITION = 0x607A
HOME_OFFSET = 0x607C
QUICK_STOP_DECELERATION = 0x6085
HOMING_METHOD = 0x6098
HOMING_SPEEDS = 0x6099
HOMING_ACCELERATION = 0x609A
INTERPOLATION_TIME_PERIOD = 0x60C2
SUPPORTED_DRIVE_MODES = 0x6502

# Communication profile (CiA 301) objects the master configures.
DEVICE_TYPE = 0x1000
ERROR_REGISTER = 0x1001
COMMUNICATION_CYCLE_PERIOD = 0x1006
CONSUMER_HEARTBEAT_TIME = 0x1016
PRODUCER_HEARTBEAT_TIME = 0x1017
IDENTITY = 0x1018

DRIVE_PROFILE_NUMBER = 402  # low 16 bits of 0x1000 for a CiA 402 device

# EMCY error codes (CiA 301 Table 21 / CiA 402 Annex) the simulator raises and the master names.
EMCY_HEARTBEAT_LOST = 0x8130
EMCY_FOLLOWING_ERROR = 0x8611
ERROR_CODE_NAMES = {
    0x0000: "no error",
    0x2310: "continuous over-current",
    0x3210: "DC-link over-voltage",
    0x4310: "drive over-temperature",
    0x5530: "encoder fault",
    EMCY_HEARTBEAT_LOST: "heartbeat lost (master disappeared)",
    EMCY_FOLLOWING_ERROR: "following error",
}


def describe_error_code(code: int) -> str:
    return f"0x{code:04X} {ERROR_CODE_NAMES.get(code, 'vendor-specific error')}"


class OperationMode(enum.IntEnum):
    """0x6060 modes of operation; bit (mode − 1) of 0x6502 says whether a drive supports it."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    HOMING = 6
    CYCLIC_SYNCHRONOUS_POSITION = 8

    @property
    def supported_modes_bit(self) -> int:
        return 1 << (self.value - 1)


class QuickStopOption(enum.IntEnum):
    """0x605A: what the drive does on a quick stop command. 0x605E uses the same ramp codes."""

    DISABLE_DRIVE = 0
    SLOW_DOWN_RAMP_THEN_DISABLE = 1
    QUICK_STOP_RAMP_THEN_DISABLE = 2
    SLOW_DOWN_RAMP_AND_STAY = 5
    QUICK_STOP_RAMP_AND_STAY = 6


# 0x605A codes after which a quick-stopped drive stays in QUICK STOP ACTIVE (transition 16 possible); with
# the others (0–4) it goes on to SWITCH ON DISABLED by itself once stopped (transition 12).
QUICK_STOP_STAY_OPTIONS = frozenset({5, 6, 7, 8})
QUICK_STOP_DISABLE_OPTIONS = frozenset({0, 1, 2, 3, 4})


class AbortConnectionOption(enum.IntEnum):
    """0x6007: what the drive does when it loses the master (heartbeat consumer timeout)."""

    NO_ACTION = 0
    FAULT = 1
    QUICK_STOP = 3


# Controlword bits outside the device-control command (CiA 402 §6.2.1).
CONTROLWORD_FAULT_RESET = 0x0080
CONTROLWORD_HOMING_START = 0x0010  # "operation mode specific" bit 4 in homing mode

# Statusword bits outside the state code (CiA 402 §6.2.2).
STATUSWORD_VOLTAGE_ENABLED = 0x0010
STATUSWORD_WARNING = 0x0080
STATUSWORD_REMOTE = 0x0200
STATUSWORD_TARGET_REACHED = 0x0400
STATUSWORD_HOMING_ATTAINED = 0x1000  # mode 6; in CSP the same bit says "drive follows the command value"
STATUSWORD_HOMING_ERROR = 0x2000  # mode 6; in CSP the same bit says "following error"

# Statusword state codes: (mask, value) per state.
STATUSWORD_CODES: dict[DriveState, tuple[int, int]] = {
    DriveState.NOT_READY_TO_SWITCH_ON: (0x4F, 0x00),
    DriveState.SWITCH_ON_DISABLED: (0x4F, 0x40),
    DriveState.READY_TO_SWITCH_ON: (0x6F, 0x21),
    DriveState.SWITCHED_ON: (0x6F, 0x23),
    DriveState.OPERATION_ENABLED: (0x6F, 0x27),
    DriveState.QUICK_STOP_ACTIVE: (0x6F, 0x07),
    DriveState.FAULT_REACTION_ACTIVE: (0x4F, 0x0F),
    DriveState.FAULT: (0x4F, 0x08),
}

# Power stages that are energised: the states in which the drive can move the axis.
POWERED_STATES = frozenset(
    {DriveState.OPERATION_ENABLED, DriveState.QUICK_STOP_ACTIVE, DriveState.FAULT_REACTION_ACTIVE}
)
FAULT_STATES = frozenset({DriveState.FAULT_REACTION_ACTIVE, DriveState.FAULT})


@dataclass(frozen=True)
class Transition:
    """One numbered transition of the CiA 402 state machine (§6.2, figure 31).

    `controlword` is what the master sends; a drive takes the transition when
    `received & match_mask == controlword & match_mask`. Internal transitions (taken by the drive
    itself: boot, fault, end of a ramp) have no controlword. `rising_edge` marks fault reset,
    which only acts on a 0 → 1 change of bit 7. `quick_stop_options`: the 0x605A codes under which
    the transition exists (None: under every code).
    """

    number: int
    source: DriveState
    target: DriveState
    command: str
    controlword: int | None
    match_mask: int = 0
    rising_edge: bool = False
    quick_stop_options: frozenset[int] | None = None

    def exists_under(self, quick_stop_option: int | None) -> bool:
        """Whether a drive with this 0x605A code has the transition (None: the code is not known)."""
        return (
            self.quick_stop_options is None or quick_stop_option is None or quick_stop_option in self.quick_stop_options
        )


S = DriveState
# The states a drive-internal fault leaves by transition 13 (every state outside the fault states).
FAULTABLE_STATES = (S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE)
TRANSITIONS: tuple[Transition, ...] = (
    Transition(1, S.NOT_READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED, "self-test done", None),
    Transition(2, S.SWITCH_ON_DISABLED, S.READY_TO_SWITCH_ON, "shutdown", 0x0006, 0x0087),
    # "Switch on" also matches "switch on + enable operation" (0x0F): the drive passes SWITCHED_ON.
    Transition(3, S.READY_TO_SWITCH_ON, S.SWITCHED_ON, "switch on", 0x0007, 0x0087),
    Transition(4, S.SWITCHED_ON, S.OPERATION_ENABLED, "enable operation", 0x000F, 0x008F),
    Transition(5, S.OPERATION_ENABLED, S.SWITCHED_ON, "disable operation", 0x0007, 0x008F),
    Transition(6, S.SWITCHED_ON, S.READY_TO_SWITCH_ON, "shutdown", 0x0006, 0x0087),
    # Transitions 7 and 10 are taken on "disable voltage" and on "quick stop" alike (§6.2, table 28).
    Transition(7, S.READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED, "disable voltage", 0x0000, 0x0082),
    Transition(7, S.READY_TO_SWITCH_ON, S.SWITCH_ON_DISABLED, "quick stop", 0x0002, 0x0086),
    Transition(8, S.OPERATION_ENABLED, S.READY_TO_SWITCH_ON, "shutdown", 0x0006, 0x0087),
    Transition(9, S.OPERATION_ENABLED, S.SWITCH_ON_DISABLED, "disable voltage", 0x0000, 0x0082),
    Transition(10, S.SWITCHED_ON, S.SWITCH_ON_DISABLED, "disable voltage", 0x0000, 0x0082),
    Transition(10, S.SWITCHED_ON, S.SWITCH_ON_DISABLED, "quick stop", 0x0002, 0x0086),
    Transition(11, S.OPERATION_ENABLED, S.QUICK_STOP_ACTIVE, "quick stop", 0x0002, 0x0086),
    Transition(12, S.QUICK_STOP_ACTIVE, S.SWITCH_ON_DISABLED, "disable voltage", 0x0000, 0x0082),
    Transition(
        12,
        S.QUICK_STOP_ACTIVE,
        S.SWITCH_ON_DISABLED,
        "quick stop done",
        None,
        quick_stop_options=QUICK_STOP_DISABLE_OPTIONS,
    ),
    *(Transition(13, source, S.FAULT_REACTION_ACTIVE, "fault", None) for source in FAULTABLE_STATES),
    Transition(14, S.FAULT_REACTION_ACTIVE, S.FAULT, "fault reaction done", None),
    Transition(15, S.FAULT, S.SWITCH_ON_DISABLED, "fault reset", 0x0080, 0x0080, rising_edge=True),
    Transition(
        16,
        S.QUICK_STOP_ACTIVE,
        S.OPERATION_ENABLED,
        "enable operation",
        0x000F,
        0x008F,
        quick_stop_options=QUICK_STOP_STAY_OPTIONS,
    ),
)
del S
FAULT_RESET_TRANSITION = 15
# The table by source state, for the per-cycle decode of every drive's controlword.
TRANSITIONS_FROM: dict[DriveState, tuple[Transition, ...]] = {
    state: tuple(t for t in TRANSITIONS if t.source == state) for state in DriveState
}

# The controlword that keeps a drive where it is (no transition out of that state matches it).
HOLD_CONTROLWORD: dict[DriveState, int] = {
    DriveState.NOT_READY_TO_SWITCH_ON: 0x0000,
    DriveState.SWITCH_ON_DISABLED: 0x0000,
    DriveState.READY_TO_SWITCH_ON: 0x0006,
    DriveState.SWITCHED_ON: 0x0007,
    DriveState.OPERATION_ENABLED: 0x000F,
    DriveState.QUICK_STOP_ACTIVE: 0x0002,
    DriveState.FAULT_REACTION_ACTIVE: 0x0000,
    DriveState.FAULT: 0x0000,
}


def _state_lookup_table() -> np.ndarray:
    """DriveState for every low byte of a statusword (the state code lives in bits 0–6)."""
    table = np.full(256, DriveState.NOT_READY_TO_SWITCH_ON, dtype=np.int8)
    for low_byte in range(256):
        for state, (mask, value) in STATUSWORD_CODES.items():
            if low_byte & mask == value:
                table[low_byte] = state
                break
    return table


STATE_BY_STATUSWORD_LOW_BYTE = _state_lookup_table()


def state_from_statusword(statusword: int) -> DriveState:
    return DriveState(int(STATE_BY_STATUSWORD_LOW_BYTE[statusword & 0xFF]))


def states_from_statuswords(statuswords: np.ndarray, out: np.ndarray) -> None:
    """Vectorised decode for the per-tick read path: `out[i] = state of statuswords[i]`."""
    np.take(STATE_BY_STATUSWORD_LOW_BYTE, statuswords & 0xFF, out=out)


def statusword_for(state: DriveState) -> int:
    return STATUSWORD_CODES[state][1]


@cache
def transition_path(
    source: DriveState, target: DriveState, quick_stop_option: int | None = None
) -> tuple[Transition, ...]:
    """Shortest sequence of commanded transitions from `source` to `target` (breadth-first search),
    for a drive with 0x605A = `quick_stop_option` (None: any).

    Raises ValueError when the table holds no commanded path (e.g. into FAULT, which only the
    drive itself can enter).
    """
    if source == target:
        return ()
    parents: dict[DriveState, Transition] = {}
    frontier = deque([source])
    while frontier:
        state = frontier.popleft()
        for transition in TRANSITIONS:
            if transition.source != state or transition.controlword is None or transition.target in parents:
                continue
            if not transition.exists_under(quick_stop_option):
                continue
            if transition.target == source:
                continue
            parents[transition.target] = transition
            if transition.target == target:
                path = [transition]
                while path[0].source != source:
                    path.insert(0, parents[path[0].source])
                return tuple(path)
            frontier.append(transition.target)
    raise ValueError(f"no commanded CiA 402 path from {source.name} to {target.name}")


def next_controlword(
    current: DriveState, target: DriveState, previous_controlword: int, quick_stop_option: int | None = None
) -> int:
    """The controlword that moves a drive one step from `current` towards `target`.

    A fault reset needs a rising edge of bit 7, so after a reset that did not take (bit 7 still set)
    the master first drops the bit for one cycle.
    """
    if current == target:
        return HOLD_CONTROLWORD[current]
    step = transition_path(current, target, quick_stop_option)[0]
    assert step.controlword is not None  # transition_path only returns commanded transitions
    if step.rising_edge and previous_controlword & step.match_mask:
        return HOLD_CONTROLWORD[current]
    return step.controlword


def commanded_transition(
    current: DriveState, controlword: int, previous_controlword: int, quick_stop_option: int | None = None
) -> Transition | None:
    """The transition a drive in `current` with 0x605A = `quick_stop_option` takes on receiving
    `controlword` (None: stay)."""
    for transition in TRANSITIONS_FROM[current]:
        if transition.controlword is None:
            continue
        if not transition.exists_under(quick_stop_option):
            continue
        if controlword & transition.match_mask != transition.controlword & transition.match_mask:
            continue
        if transition.rising_edge and previous_controlword & transition.match_mask:
            continue
        return transition
    return None


def internal_transition(source: DriveState, target: DriveState) -> Transition:
    """The drive-initiated transition from `source` to `target` (boot, fault, end of a ramp)."""
    for transition in TRANSITIONS:
        if transition.source == source and transition.target == target and transition.controlword is None:
            return transition
    raise ValueError(f"no internal CiA 402 transition from {source.name} to {target.name}")


def quick_stop_completion(quick_stop_option: int) -> Transition | None:
    """What a quick-stopped drive does by itself once at standstill: transition 12 to SWITCH ON
    DISABLED under a disable option of 0x605A, None (stay, holding) under a stay option."""
    for transition in TRANSITIONS:
        if (
            transition.source == DriveState.QUICK_STOP_ACTIVE
            and transition.target == DriveState.SWITCH_ON_DISABLED
            and transition.controlword is None
            and transition.exists_under(quick_stop_option)
        ):
            return transition
    return None


def quick_stop_target(state: DriveState) -> DriveState:
    """Where a master sends a drive on a quick stop: an enabled drive ramps down in QUICK STOP ACTIVE, a
    stopping or faulted one carries on, any other is disabled."""
    if state == DriveState.OPERATION_ENABLED:
        return DriveState.QUICK_STOP_ACTIVE
    if state == DriveState.QUICK_STOP_ACTIVE or state in FAULT_STATES:
        return state
    return DriveState.SWITCH_ON_DISABLED


class DriveStateMachines:
    """The power state machines of simulated drives, one per axis, changed only through `TRANSITIONS`.

    `command()` is a master and a drive in one: the master's controlwords (`next_controlword`) walk the
    table's path, and each is decoded as a drive decodes it (`commanded_transition`). `internal()` and
    `fault()` are the drive's own transitions (self-test, fault, end of a ramp). The MuJoCo servo drives
    and the kinematic backend use it, so every backend's drives agree with the simulated CANopen drive.
    """

    def __init__(self, count: int, quick_stop_option: int = QuickStopOption.QUICK_STOP_RAMP_AND_STAY) -> None:
        self.states = np.full(count, DriveState.NOT_READY_TO_SWITCH_ON, dtype=np.int8)
        self.quick_stop_option = quick_stop_option
        self._controlwords = np.zeros(count, dtype=np.int64)
        self.internal(DriveState.NOT_READY_TO_SWITCH_ON, DriveState.SWITCH_ON_DISABLED)  # self-test done

    def _axes(self, axes: np.ndarray | None) -> np.ndarray:
        return np.arange(self.states.size) if axes is None else np.flatnonzero(axes)

    def command(self, target: DriveState, axes: np.ndarray | None = None, *, reset_faults: bool = False) -> None:
        """Take each axis (all, or where the mask `axes` is set) to `target` by controlwords. An axis with
        no commanded path stays; a faulted axis is reset (transition 15) only with `reset_faults`."""
        for axis in self._axes(axes):
            state = DriveState(int(self.states[axis]))
            previous = int(self._controlwords[axis])
            for _ in range(len(TRANSITIONS)):  # at most one pass over the table; a rising edge needs two words
                if state == target:
                    break
                try:
                    step = transition_path(state, target, self.quick_stop_option)[0]
                except ValueError:
                    break
                if step.number == FAULT_RESET_TRANSITION and not reset_faults:
                    break
                word = next_controlword(state, target, previous, self.quick_stop_option)
                taken = commanded_transition(state, word, previous, self.quick_stop_option)
                previous = word
                if taken is not None:
                    state = taken.target
            self.states[axis] = state
            self._controlwords[axis] = previous

    def internal(self, source: DriveState, target: DriveState, axes: np.ndarray | None = None) -> None:
        """The drive-initiated transition `source` → `target` on each axis (of the mask) that is in `source`."""
        transition = internal_transition(source, target)
        chosen = self.states == transition.source
        if axes is not None:
            chosen &= axes
        self.states[chosen] = transition.target

    def quick_stop(self, axes: np.ndarray | None = None) -> None:
        for axis in self._axes(axes):
            self.command(quick_stop_target(DriveState(int(self.states[axis]))), self._one(axis))

    def quick_stop_done(self, axes: np.ndarray) -> None:
        """The quick-stop ramp ended on these axes: transition 12 under a disable option, else they stay."""
        completion = quick_stop_completion(self.quick_stop_option)
        if completion is not None:
            self.internal(completion.source, completion.target, axes)

    def fault(self, axes: np.ndarray | None = None) -> None:
        """A drive-internal fault (transition 13) on each axis (of the mask) not already faulted."""
        for source in FAULTABLE_STATES:
            self.internal(source, DriveState.FAULT_REACTION_ACTIVE, axes)

    def disable(self, axes: np.ndarray | None = None) -> None:
        """Power off every axis (of the mask) that is not faulted: a disable never resets a fault."""
        powered = ~np.isin(self.states, [DriveState.FAULT_REACTION_ACTIVE, DriveState.FAULT])
        self.command(DriveState.SWITCH_ON_DISABLED, powered if axes is None else powered & axes)

    def _one(self, axis: int) -> np.ndarray:
        mask = np.zeros(self.states.size, dtype=bool)
        mask[axis] = True
        return mask

    def in_state(self, state: DriveState) -> np.ndarray:
        return self.states == state
