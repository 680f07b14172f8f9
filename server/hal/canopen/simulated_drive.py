"""A simulated CiA 402 servo drive on python-canopen's LocalNode, and a rack of them on one bus.

Each drive answers SDO from its EDS, boots and follows NMT, takes its PDO mapping from what the master
wrote into its object dictionary, and on every SYNC: integrates its servo over one communication
cycle (0x1006) under the last latched command, latches the new synchronous RPDO (controlword through
the shared `cia402` transition table, target position, mode), and answers with its synchronous TPDOs.
It is a standard drive for any master, not only this product's: the controlword, the mode (0x6060)
and the target (0x607A) act when written by SDO or by an event-driven RPDO (transmission type 254/255)
as they do from a SYNC-ed one; 0x6061 shows the mode in effect, and a mode it does not implement is
refused (SDO abort 0x06090030; 0x6502 reports only the implemented modes); event-driven TPDOs are sent
on change, at the event timer (sub-index 5) and no faster than the inhibit time (sub-index 3). A drive
whose RPDOs are not synchronous runs on its own clock. The servo is a
second-order position loop with velocity and acceleration feed-forward from the CSP targets, the way a
drive interpolates between SYNCs. It homes (0x6098 methods 17, 18, 35, 37), ramps down on quick stop
(0x605A) and fault reaction (0x605E) at 0x6085, faults on following error (0x6065/0x6066), and consumes
the master's heartbeat (0x1016): when the master disappears it applies 0x6007 on its own clock.

The rack shares one bus connection (one receive thread) among its drives, plus one watchdog thread
that runs the heartbeat consumers and, when SYNC stops, keeps time for drives that are ramping down or
have lost the master. A merely late master never advances a drive: SYNC is its time base.
Works on python-can's `virtual` bus and on Linux `vcan`/socketcan.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import can
import canopen
from canopen.sdo import SdoAbortedError

from server.hal.base import DriveState
from server.hal.canopen import cia402
from server.hal.canopen.pdo import CAN_ERR_BUSOFF, SYNC_COB_ID, PdoCodec
from server.hal.canopen.units import DriveConfiguration

logger = logging.getLogger(__name__)

SDO_ABORT_VALUE_RANGE = 0x06090030
NMT_START, NMT_RESET_NODE, NMT_RESET_COMMUNICATION = 0x01, 0x81, 0x82
NMT_OPERATIONAL = "OPERATIONAL"
SUPPORTED_HOMING_METHODS = frozenset({17, 18, 35, 37})
IMPLEMENTED_MODES = (cia402.OperationMode.CYCLIC_SYNCHRONOUS_POSITION, cia402.OperationMode.HOMING)
SYNCHRONOUS_TRANSMISSION = range(0, 241)  # CiA 301 transmission types that act on / answer SYNC
EVENT_DRIVEN_TRANSMISSION = (254, 255)
WATCHDOG_PERIOD_S = 0.005
INTEGRATION_STEP_S = 0.001  # servo integration sub-step; semi-implicit Euler is stable for ωn·h = 0.25


@dataclass
class ServoModel:
    """Mechanics and position loop of one simulated axis."""

    counts_per_m: float
    rated_force_n: float
    moving_mass_kg: float = 30.0  # slider carriage plus its share of rod and platform
    natural_frequency_hz: float = 40.0
    damping_ratio: float = 1.0
    max_acceleration_m_s2: float = 60.0
    travel_m: float = 1.8  # switch-to-switch distance for homing methods 17 and 18


@dataclass
class EventTpdo:
    """An event-driven TPDO: sent when its frame changes, at the event timer, never within the inhibit time."""

    codec: PdoCodec
    inhibit_s: float
    event_timer_s: float
    last_frame: bytes | None = None
    last_sent_s: float = -math.inf

    def due(self, frame: bytes, now_s: float) -> bool:
        if now_s - self.last_sent_s < self.inhibit_s:
            return False
        timer_expired = self.event_timer_s > 0.0 and now_s - self.last_sent_s >= self.event_timer_s
        return frame != self.last_frame or timer_expired


@dataclass
class DriveTrace:
    """What a test needs to judge the drive: state changes, EMCYs and the hardest stop deceleration."""

    transitions: list[tuple[float, DriveState, DriveState, str]] = field(default_factory=list)
    emergencies: list[int] = field(default_factory=list)
    peak_stop_deceleration_counts_s2: float = 0.0
    states_seen: set[DriveState] = field(default_factory=set)


class SimulatedDrive:
    """One CiA 402 drive behind a LocalNode. Call its methods with the rack's lock held."""

    def __init__(
        self,
        node: canopen.LocalNode,
        servo: ServoModel,
        start_position_m: float,
        lock: threading.RLock | None = None,
    ) -> None:
        self.node = node
        self.lock = lock if lock is not None else threading.RLock()  # the rack's: SDO and PDO arrive on the bus thread
        self.servo = servo
        self.trace = DriveTrace()
        self.connected = True
        self.state = DriveState.NOT_READY_TO_SWITCH_ON
        self.true_position_counts = start_position_m * servo.counts_per_m  # switch edge of method 17 at 0
        self.velocity_counts_s = 0.0
        self.acceleration_counts_s2 = 0.0
        self.home_reference_counts = self.true_position_counts  # encoder reads 0 at power-up
        self.homed = False
        self.error_code = 0
        self._pending_fault: int | None = None
        self._controlword = 0
        self._mode = 0
        self._mode_display = 0
        self._target_counts = 0.0
        self._reference_counts = 0.0
        self._feedforward_velocity = 0.0
        self._feedforward_acceleration = 0.0
        self._homing_phase = 0  # 0 idle, 1 search switch, 2 back off to the edge
        self._homing_attained = False
        self._following_error_since_s: float | None = None
        self._following_error_active = False
        self._master_heartbeat_id: int | None = None
        self._master_heartbeat_timeout_s = 0.0
        self._master_heartbeat_seen_s: float | None = None
        self._heartbeat_lost = False
        self.drive_time_s = 0.0  # the drive's own clock: sum of integrated cycles
        self.last_step_s = time.monotonic()
        self.last_sync_s = 0.0
        self._rpdo_codecs: list[tuple[canopen.pdo.PdoMap, PdoCodec]] = []
        self._event_rpdo_codecs: dict[int, PdoCodec] = {}
        self._tpdo_codecs: list[PdoCodec] = []
        self._event_tpdos: list[EventTpdo] = []
        self._synchronous = False  # whether SYNC is the time base (a synchronous RPDO is mapped)
        self._parameters: dict[tuple[int, int], int] = {}
        if cia402.SUPPORTED_DRIVE_MODES in node.object_dictionary:  # report only what this drive implements
            implemented = sum(mode.supported_modes_bit for mode in IMPLEMENTED_MODES)
            listed = self.parameter(cia402.SUPPORTED_DRIVE_MODES)
            self.override(cia402.SUPPORTED_DRIVE_MODES, 0, listed & implemented)
        node.add_write_callback(self._on_sdo_write)
        node.add_read_callback(self._on_sdo_read)
        self._take(cia402.internal_transition(DriveState.NOT_READY_TO_SWITCH_ON, DriveState.SWITCH_ON_DISABLED))

    # --- parameters (object dictionary) -----------------------------------------------------------

    def parameter(self, index: int, subindex: int = 0) -> int:
        """Current value of a configuration object: written over SDO, else the EDS default."""
        if (index, subindex) in self._parameters:
            return self._parameters[(index, subindex)]
        entry = self.node.object_dictionary[index]
        variable = entry if isinstance(entry, canopen.objectdictionary.ODVariable) else entry[subindex]
        value = variable.value if variable.value is not None else variable.default
        assert isinstance(value, int), f"0x{index:04X}:{subindex:02X} is not an integer object"
        return value

    def override(self, index: int, subindex: int, value: int) -> None:
        """Change a value the master cannot write (read-only objects: identity, supported modes)."""
        self._parameters[(index, subindex)] = value

    def _on_sdo_write(self, index: int, subindex: int, od: canopen.objectdictionary.ODVariable, data: bytes) -> None:
        value = od.decode_raw(data)
        if not isinstance(value, int):
            return  # strings and domains: stored by the LocalNode, no behaviour here
        if index == cia402.HOMING_METHOD and value not in SUPPORTED_HOMING_METHODS:
            raise SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        if index == cia402.ABORT_CONNECTION_OPTION_CODE and value not in set(cia402.AbortConnectionOption):
            raise SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        if index in (cia402.QUICK_STOP_OPTION_CODE, cia402.FAULT_REACTION_OPTION_CODE) and value not in (1, 2, 5, 6):
            raise SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        if index == cia402.MODES_OF_OPERATION and not self.implements_mode(value):
            raise SdoAbortedError(SDO_ABORT_VALUE_RANGE)
        self._parameters[(index, subindex)] = value
        if index == cia402.CONSUMER_HEARTBEAT_TIME and subindex == 1:
            self._configure_heartbeat_consumer(value)
        if index in (cia402.CONTROLWORD, cia402.MODES_OF_OPERATION, cia402.TARGET_POSITION):
            with self.lock:  # acted on at once, as from an event-driven RPDO
                self._latch({index: value}, synchronous=False)
                self.send_event_tpdos(time.monotonic())

    def implements_mode(self, mode: int) -> bool:
        """Whether 0x6060 = `mode` can take effect: a mode this drive implements and 0x6502 reports."""
        listed = cia402.SUPPORTED_DRIVE_MODES in self.node.object_dictionary
        supported = self.parameter(cia402.SUPPORTED_DRIVE_MODES) if listed else ~0  # no 0x6502: all it implements
        return any(mode == m and supported & m.supported_modes_bit for m in IMPLEMENTED_MODES)

    def _on_sdo_read(self, index: int, subindex: int, od: canopen.objectdictionary.ODVariable) -> int | None:
        live = self._live_values()
        if index in live:
            return live[index]
        if (index, subindex) in self._parameters:
            return self._parameters[(index, subindex)]
        return None

    def _live_values(self) -> dict[int, int]:
        return {
            cia402.STATUSWORD: self.statusword(),
            cia402.POSITION_ACTUAL: self.position_actual_counts(),
            cia402.VELOCITY_ACTUAL: round(self.velocity_counts_s),
            cia402.TORQUE_ACTUAL: self.torque_actual_per_mille(),
            cia402.ERROR_CODE: self.error_code,
            cia402.MODES_OF_OPERATION_DISPLAY: self._mode_display,
            cia402.ERROR_REGISTER: 1 if self.error_code else 0,
        }

    # --- reported values --------------------------------------------------------------------------

    def position_actual_counts(self) -> int:
        return round(self.true_position_counts - self.home_reference_counts)

    def torque_actual_per_mille(self) -> int:
        force_n = self.servo.moving_mass_kg * self.acceleration_counts_s2 / self.servo.counts_per_m
        return max(-32768, min(32767, round(1000.0 * force_n / self.servo.rated_force_n)))

    def statusword(self) -> int:
        word = cia402.statusword_for(self.state) | cia402.STATUSWORD_REMOTE
        if self.state in (DriveState.SWITCHED_ON, *cia402.POWERED_STATES):
            word |= cia402.STATUSWORD_VOLTAGE_ENABLED
        standstill = self.velocity_counts_s == 0.0
        if self._mode_display == cia402.OperationMode.HOMING:
            if self._homing_attained:
                word |= cia402.STATUSWORD_HOMING_ATTAINED
            if self._homing_phase == 0:
                word |= cia402.STATUSWORD_TARGET_REACHED
        elif self._mode_display == cia402.OperationMode.CYCLIC_SYNCHRONOUS_POSITION:
            if self.state == DriveState.OPERATION_ENABLED:
                word |= cia402.STATUSWORD_HOMING_ATTAINED  # CSP: "drive follows the command value"
            if self._following_error_active:
                word |= cia402.STATUSWORD_HOMING_ERROR  # CSP: "following error"
        if self.state == DriveState.QUICK_STOP_ACTIVE and standstill:
            word |= cia402.STATUSWORD_TARGET_REACHED
        return word

    # --- NMT and PDO configuration ------------------------------------------------------------------

    def boot(self) -> None:
        """Power-on or NMT reset: boot-up message, then PRE-OPERATIONAL with the heartbeat producer."""
        self.node.nmt.stop_heartbeat()
        self.node.nmt.send_command(NMT_RESET_NODE)  # state INITIALISING: sends the boot-up frame
        self.node.nmt.send_command(0x80)  # PRE-OPERATIONAL: starts the 0x1017 heartbeat if set

    def on_nmt(self, command: int) -> None:
        if command == NMT_START:
            self._load_pdo_mapping()
        elif command in (NMT_RESET_NODE, NMT_RESET_COMMUNICATION):
            self._reset(application=command == NMT_RESET_NODE)
            self.boot()

    def _reset(self, *, application: bool) -> None:
        communication = {key for key in self._parameters if key[0] < 0x2000}
        for key in communication | (set(self._parameters) if application else set()):
            # Read-only overrides (identity, modes) model the device itself, not its settings.
            entry = self.node.object_dictionary[key[0]]
            variable = entry if isinstance(entry, canopen.objectdictionary.ODVariable) else entry[key[1]]
            if variable.writable:
                del self._parameters[key]
        self.node.data_store.clear()
        self._master_heartbeat_id = None
        self._heartbeat_lost = False
        self._rpdo_codecs, self._tpdo_codecs = [], []
        self._event_rpdo_codecs, self._event_tpdos, self._synchronous = {}, [], False
        if application:
            self.homed = self._homing_attained = False
            self.home_reference_counts = self.true_position_counts
            self.error_code = 0
            self._enter(DriveState.NOT_READY_TO_SWITCH_ON, "reset node")
            self._take(cia402.internal_transition(DriveState.NOT_READY_TO_SWITCH_ON, DriveState.SWITCH_ON_DISABLED))

    def _load_pdo_mapping(self) -> None:
        """Read the mapping the master wrote (0x1400/0x1600, 0x1800/0x1A00) and build codecs from it.

        Synchronous RPDOs are latched on SYNC; event-driven ones act on reception. Synchronous TPDOs
        (types 1–240) answer every SYNC; event-driven ones (254/255) are sent on change, starting now."""
        od = self.node.object_dictionary
        self.node.rpdo.read()
        self.node.tpdo.read()
        assert self.node.rpdo.map is not None and self.node.tpdo.map is not None

        def codec(pdo: canopen.pdo.PdoMap) -> PdoCodec:
            assert pdo.cob_id is not None  # read() set it
            return PdoCodec.from_mapping(pdo.cob_id, [(v.index, v.length) for v in pdo.map], od)

        rpdos = [pdo for pdo in self.node.rpdo.map.values() if pdo.enabled and pdo.map]
        self._rpdo_codecs = [(pdo, codec(pdo)) for pdo in rpdos if pdo.trans_type in SYNCHRONOUS_TRANSMISSION]
        self._event_rpdo_codecs = {
            pdo.cob_id: codec(pdo) for pdo in rpdos if pdo.trans_type in EVENT_DRIVEN_TRANSMISSION
        }
        for pdo in rpdos:
            pdo.callbacks[:] = [self._on_event_rpdo] if pdo.cob_id in self._event_rpdo_codecs else []
        self._synchronous = bool(self._rpdo_codecs)
        tpdos = [pdo for pdo in self.node.tpdo.map.values() if pdo.enabled and pdo.map]
        self._tpdo_codecs = [codec(pdo) for pdo in tpdos if pdo.trans_type is not None and 1 <= pdo.trans_type <= 240]
        self._event_tpdos = [
            EventTpdo(codec(pdo), (pdo.inhibit_time or 0) * 1e-4, (pdo.event_timer or 0) * 1e-3)
            for pdo in tpdos
            if pdo.trans_type in EVENT_DRIVEN_TRANSMISSION
        ]
        self.send_event_tpdos(time.monotonic())

    def _on_event_rpdo(self, pdo: canopen.pdo.PdoMap) -> None:
        """An event-driven RPDO arrived (bus thread): act on it now, no SYNC needed."""
        codec = self._event_rpdo_codecs.get(pdo.cob_id or 0)
        with self.lock:
            if codec is None or not self.connected or self.node.nmt.state != NMT_OPERATIONAL:
                return
            self._latch(dict(zip(codec.indices, codec.unpack(pdo.data), strict=True)), synchronous=False)
            self.send_event_tpdos(time.monotonic())

    def send_event_tpdos(self, now_s: float) -> None:
        """Every event-driven TPDO whose frame changed or whose event timer expired (inhibit time kept)."""
        if not self._event_tpdos or not self.connected or self.node.nmt.state != NMT_OPERATIONAL:
            return
        live = self._live_values()
        for tpdo in self._event_tpdos:
            frame = tpdo.codec.pack([live[index] for index in tpdo.codec.indices])
            if tpdo.due(frame, now_s):
                self.node.network.send_message(tpdo.codec.cob_id, frame)
                tpdo.last_frame, tpdo.last_sent_s = frame, now_s

    # --- heartbeat consumer -------------------------------------------------------------------------

    def _configure_heartbeat_consumer(self, value: int) -> None:
        producer_id, timeout_ms = (value >> 16) & 0x7F, value & 0xFFFF
        self._master_heartbeat_id = producer_id if timeout_ms else None
        self._master_heartbeat_timeout_s = timeout_ms / 1000.0
        self._master_heartbeat_seen_s = None  # CiA 301: monitoring starts with the first heartbeat

    @property
    def master_heartbeat_seen_s(self) -> float | None:
        """When the master's heartbeat last arrived (None: not yet, so not monitored)."""
        return self._master_heartbeat_seen_s

    def on_heartbeat(self, producer_id: int, now_s: float) -> None:
        if producer_id == self._master_heartbeat_id:
            self._master_heartbeat_seen_s = now_s
            self._heartbeat_lost = False

    @property
    def synchronous(self) -> bool:
        """Whether SYNC is this drive's time base (a synchronous RPDO is mapped)."""
        return self._synchronous

    def runs_on_own_clock(self) -> bool:
        """A ramp in progress, or a lost master: then time passes without SYNC.

        A master that is merely late (a stalled host) does not advance a drive in CSP: its time base
        is the SYNC, as on a real drive.
        """
        ramping = self.state in (DriveState.QUICK_STOP_ACTIVE, DriveState.FAULT_REACTION_ACTIVE)
        # Without a synchronous RPDO (SDO or event-driven control) the drive's own clock is its time base
        # whenever there is something to move or a fault to raise.
        asynchronous = not self._synchronous and (
            self.state in cia402.POWERED_STATES or self._pending_fault is not None
        )
        return ramping or self._heartbeat_lost or not self.connected or asynchronous

    def check_heartbeat(self, now_s: float) -> None:
        seen = self._master_heartbeat_seen_s
        if seen is None or self._heartbeat_lost or now_s - seen <= self._master_heartbeat_timeout_s:
            return
        self._heartbeat_lost = True
        option = self.parameter(cia402.ABORT_CONNECTION_OPTION_CODE)
        logger.warning("node %d: master heartbeat lost; abort connection option %d", self.node.id, option)
        if option == cia402.AbortConnectionOption.FAULT:
            self.inject_fault(cia402.EMCY_HEARTBEAT_LOST)
        else:
            self._emergency(cia402.EMCY_HEARTBEAT_LOST)
            if option == cia402.AbortConnectionOption.QUICK_STOP:  # as if the master had sent "quick stop"
                quick_stop = cia402.HOLD_CONTROLWORD[DriveState.QUICK_STOP_ACTIVE]
                stop = cia402.commanded_transition(
                    self.state, quick_stop, self._controlword, self.parameter(cia402.QUICK_STOP_OPTION_CODE)
                )
                if stop is not None:
                    self._enter(stop.target, "heartbeat lost")

    # --- faults -------------------------------------------------------------------------------------

    def inject_fault(self, error_code: int) -> None:
        """A drive-internal fault (over-current, encoder…): fault reaction at the next step."""
        self._pending_fault = error_code

    def _emergency(self, code: int) -> None:
        self.trace.emergencies.append(code)
        if self.connected:
            self.node.emcy.send(code, 1 if code else 0)

    def _raise_pending_fault(self) -> None:
        code, self._pending_fault = self._pending_fault, None
        if code is None or self.state in cia402.FAULT_STATES:
            return
        self.error_code = code
        self._emergency(code)
        fault = cia402.internal_transition(self.state, DriveState.FAULT_REACTION_ACTIVE)
        self._enter(fault.target, cia402.describe_error_code(code))
        if self.velocity_counts_s == 0.0 or self.parameter(cia402.FAULT_REACTION_OPTION_CODE) == 0:
            self._stop_power()
            self._take(cia402.internal_transition(DriveState.FAULT_REACTION_ACTIVE, DriveState.FAULT))

    # --- the cycle ----------------------------------------------------------------------------------

    def on_sync(self, now_s: float) -> None:
        """One communication cycle: integrate, latch the RPDO, transmit the TPDOs."""
        if not self.connected or self.node.nmt.state != NMT_OPERATIONAL:
            return
        self.last_sync_s = now_s
        self.advance(self.parameter(cia402.COMMUNICATION_CYCLE_PERIOD) / 1e6, synchronous=True)
        self.last_step_s = now_s
        for pdo, codec in self._rpdo_codecs:
            if pdo.is_received:
                self._latch(dict(zip(codec.indices, codec.unpack(pdo.data), strict=True)), synchronous=True)
        live = self._live_values()
        for codec in self._tpdo_codecs:
            self.node.network.send_message(codec.cob_id, codec.pack([live[index] for index in codec.indices]))
        self.send_event_tpdos(now_s)

    def _latch(self, values: Mapping[int, int], *, synchronous: bool) -> None:
        """Act on received command objects. A synchronous CSP target is the next interpolation point, one
        cycle (0x1006) on, with velocity and acceleration feed-forward; an asynchronous one (SDO or an
        event-driven RPDO) is a new set-point the position loop goes to."""
        period_s = self.parameter(cia402.COMMUNICATION_CYCLE_PERIOD) / 1e6
        if cia402.MODES_OF_OPERATION in values:
            self._set_mode(values[cia402.MODES_OF_OPERATION])
        csp = self._mode_display == cia402.OperationMode.CYCLIC_SYNCHRONOUS_POSITION
        if cia402.TARGET_POSITION in values and csp and self.state == DriveState.OPERATION_ENABLED:
            target = values[cia402.TARGET_POSITION] + self.home_reference_counts
            previous = self._target_counts
            self._target_counts = target
            if synchronous and period_s > 0:
                self._reference_counts = previous
                velocity = (target - previous) / period_s
                self._feedforward_acceleration = (velocity - self._feedforward_velocity) / period_s
                self._feedforward_velocity = velocity
            else:
                self._reference_counts = target
                self._feedforward_velocity = self._feedforward_acceleration = 0.0
        if cia402.CONTROLWORD in values:
            self._apply_controlword(values[cia402.CONTROLWORD])

    def _set_mode(self, mode: int) -> None:
        if mode == self._mode:
            return
        self._mode = mode
        if self.implements_mode(mode):  # otherwise 0x6061 keeps showing the mode still in effect
            self._mode_display = mode
            self._homing_phase = 0

    def _apply_controlword(self, controlword: int) -> None:
        previous, self._controlword = self._controlword, controlword
        option = self.parameter(cia402.QUICK_STOP_OPTION_CODE)
        transition = cia402.commanded_transition(self.state, controlword, previous, option)
        if transition is not None:
            if transition.number == 15 and self._heartbeat_lost:
                return  # the cause persists: a fault reset cannot clear a lost master
            if transition.number == 15:
                self.error_code = 0
                self._emergency(0)
            if transition.target == DriveState.OPERATION_ENABLED:
                self._hold_here()
            self._enter(transition.target, transition.command)
        homing = self._mode_display == cia402.OperationMode.HOMING and self.state == DriveState.OPERATION_ENABLED
        start_edge = controlword & ~previous & cia402.CONTROLWORD_HOMING_START
        if homing and start_edge:
            self._start_homing()

    def _hold_here(self) -> None:
        """Enabling the power stage holds the current position: no jump towards an old target."""
        self._target_counts = float(round(self.true_position_counts))
        self._reference_counts = self._target_counts
        self._feedforward_velocity = self._feedforward_acceleration = 0.0

    def _take(self, transition: cia402.Transition) -> None:
        self._enter(transition.target, transition.command)

    def _enter(self, state: DriveState, reason: str) -> None:
        if state != self.state:
            self.trace.transitions.append((time.monotonic(), self.state, state, reason))
            self.trace.states_seen.add(state)
            self.state = state

    def advance(self, dt_s: float, *, synchronous: bool) -> None:
        """Integrate the axis over `dt_s`; without SYNC the command holds (no feed-forward)."""
        self._raise_pending_fault()
        if not synchronous:
            self._feedforward_velocity = self._feedforward_acceleration = 0.0
        self.drive_time_s += dt_s
        steps = max(1, math.ceil(dt_s / INTEGRATION_STEP_S - 1e-9))
        for _ in range(steps):
            self._integrate(dt_s / steps)
        if (
            self.state == DriveState.OPERATION_ENABLED
            and self._mode_display == cia402.OperationMode.CYCLIC_SYNCHRONOUS_POSITION
        ):
            self._monitor_following_error()

    def _integrate(self, h: float) -> None:
        state = self.state
        if state == DriveState.OPERATION_ENABLED:
            if self._mode_display == cia402.OperationMode.HOMING and self._homing_phase:
                self._homing_step(h)
            else:
                self._servo_step(h)
        elif state in (DriveState.QUICK_STOP_ACTIVE, DriveState.FAULT_REACTION_ACTIVE):
            self._stop_step(h)
        else:
            self._stop_power()

    def _servo_step(self, h: float) -> None:
        omega = 2.0 * math.pi * self.servo.natural_frequency_hz
        error = self._reference_counts - self.true_position_counts
        demand = (
            self._feedforward_acceleration
            + omega * omega * error
            + 2.0 * self.servo.damping_ratio * omega * (self._feedforward_velocity - self.velocity_counts_s)
        )
        self._move(h, demand)
        self._reference_counts += self._feedforward_velocity * h
        if self._feedforward_velocity == 0.0:
            self._reference_counts = self._target_counts

    def _move(self, h: float, demand_counts_s2: float) -> None:
        limit = self.servo.max_acceleration_m_s2 * self.servo.counts_per_m
        self.acceleration_counts_s2 = max(-limit, min(limit, demand_counts_s2))
        self.velocity_counts_s += self.acceleration_counts_s2 * h
        self.true_position_counts += self.velocity_counts_s * h

    def _stop_step(self, h: float) -> None:
        """Quick-stop / fault-reaction ramp at 0x6085 down to standstill, then the option's end state."""
        deceleration = float(self.parameter(cia402.QUICK_STOP_DECELERATION))
        speed = abs(self.velocity_counts_s)
        new_speed = max(0.0, speed - deceleration * h)
        self.acceleration_counts_s2 = -math.copysign((speed - new_speed) / h, self.velocity_counts_s)
        self.trace.peak_stop_deceleration_counts_s2 = max(
            self.trace.peak_stop_deceleration_counts_s2, abs(self.acceleration_counts_s2)
        )
        self.velocity_counts_s = math.copysign(new_speed, self.velocity_counts_s) if new_speed else 0.0
        self.true_position_counts += self.velocity_counts_s * h
        if new_speed > 0.0:
            return
        if self.state == DriveState.FAULT_REACTION_ACTIVE:
            self._stop_power()
            self._take(cia402.internal_transition(DriveState.FAULT_REACTION_ACTIVE, DriveState.FAULT))
            return
        completion = cia402.quick_stop_completion(self.parameter(cia402.QUICK_STOP_OPTION_CODE))
        if completion is not None:
            self._stop_power()
            self._take(completion)
        else:
            self._hold_here()

    def _stop_power(self) -> None:
        """Power stage off: the holding brake stops the axis."""
        self.velocity_counts_s = self.acceleration_counts_s2 = 0.0

    # --- homing ---------------------------------------------------------------------------------

    def _start_homing(self) -> None:
        method = self.parameter(cia402.HOMING_METHOD)
        self._homing_attained = False
        if method in (35, 37):
            self._finish_homing()
        else:
            self._homing_phase = 1

    def _homing_step(self, h: float) -> None:
        method = self.parameter(cia402.HOMING_METHOD)
        outward = 1.0 if method == 17 else -1.0  # direction away from the switch
        edge = 0.0 if method == 17 else self.servo.travel_m * self.servo.counts_per_m
        beyond_edge = (self.true_position_counts - edge) * outward <= 0.0
        if self._homing_phase == 1 and beyond_edge:
            self._homing_phase = 2
        if self._homing_phase == 2 and not beyond_edge and self.velocity_counts_s * outward >= 0.0:
            self.true_position_counts = edge  # the zero-speed approach stops on the switch edge
            self._finish_homing()
            return
        speed_index = 1 if self._homing_phase == 1 else 2
        wanted = self.parameter(cia402.HOMING_SPEEDS, speed_index) * (-outward if self._homing_phase == 1 else outward)
        acceleration = float(self.parameter(cia402.HOMING_ACCELERATION))
        change = max(-acceleration * h, min(acceleration * h, wanted - self.velocity_counts_s))
        self._move(h, change / h)

    def _finish_homing(self) -> None:
        self._stop_power()
        self.home_reference_counts = self.true_position_counts - self.parameter(cia402.HOME_OFFSET)
        self._homing_phase = 0
        self._homing_attained = self.homed = True
        self._hold_here()

    def _monitor_following_error(self) -> None:
        window = self.parameter(cia402.FOLLOWING_ERROR_WINDOW)
        outside = abs(self._target_counts - self.true_position_counts) > window
        now = self.drive_time_s
        if not outside:
            self._following_error_since_s = None
            self._following_error_active = False
            return
        if self._following_error_since_s is None:
            self._following_error_since_s = now
        self._following_error_active = True
        if now - self._following_error_since_s >= self.parameter(cia402.FOLLOWING_ERROR_TIMEOUT) / 1e3:
            self.inject_fault(cia402.EMCY_FOLLOWING_ERROR)

    def unplug(self) -> None:
        """The drive stops answering (cable cut): no heartbeat, SDO, PDO; its own watchdog still runs."""
        self.connected = False
        self.node.nmt.stop_heartbeat()
        network = self.node.network
        network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
        network.unsubscribe(0, self.node.nmt.on_command)


class SimulatedDriveRack:
    """Simulated drives for the nodes of a drive configuration, sharing one connection to the bus.

    Use as a context manager or call `start()` / `shutdown()`; shutdown stops every thread it started.
    """

    def __init__(
        self,
        configuration: DriveConfiguration,
        *,
        interface: str,
        channel: str,
        node_ids: list[int] | None = None,
        eds_overrides: Mapping[int, Path] | None = None,
        start_positions_m: Mapping[int, float] | None = None,
        moving_mass_kg: float = 30.0,
    ) -> None:
        self.configuration = configuration
        self.interface = interface
        self.channel = channel
        axes = {axis.node_id: axis for axis in configuration.axes}
        self.node_ids = list(axes) if node_ids is None else node_ids
        unknown = [n for n in self.node_ids if n not in axes]
        if unknown:
            raise ValueError(f"node_ids: {unknown} not in the drive configuration {sorted(axes)}")
        self._axes = axes
        self._eds_overrides = dict(eds_overrides or {})
        # Drives power up a little outside their home switch, each at a different place.
        self._start_positions_m = {n: 0.012 + 0.002 * i for i, n in enumerate(self.node_ids)}
        self._start_positions_m.update(start_positions_m or {})
        self._moving_mass_kg = moving_mass_kg
        self.lock = threading.RLock()
        self.network: canopen.Network | None = None
        self.drives: dict[int, SimulatedDrive] = {}
        self._stop = threading.Event()
        self._watchdog: threading.Thread | None = None

    def __enter__(self) -> SimulatedDriveRack:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()

    def drive(self, node_id: int) -> SimulatedDrive:
        return self.drives[node_id]

    def start(self) -> None:
        network = canopen.Network()
        network.NOTIFIER_CYCLE = 0.05  # a short receive timeout lets shutdown join the thread quickly
        for node_id in self.node_ids:
            drive_type = self._axes[node_id].drive_type
            eds = self._eds_overrides.get(node_id, drive_type.eds_path)
            node = network.create_node(node_id, str(eds))
            servo = ServoModel(drive_type.counts_per_m, drive_type.rated_force_n, moving_mass_kg=self._moving_mass_kg)
            self.drives[node_id] = SimulatedDrive(node, servo, self._start_positions_m[node_id], self.lock)
        network.subscribe(SYNC_COB_ID, self._on_sync)
        network.subscribe(0, self._on_nmt)
        for producer_id in range(1, 128):
            network.subscribe(0x700 + producer_id, self._on_heartbeat)
        network.connect(interface=self.interface, channel=self.channel, receive_own_messages=False)
        self.network = network
        with self.lock:
            for drive in self.drives.values():
                drive.boot()
        self._watchdog = threading.Thread(target=self._watch, name=f"sim-drives-{self.channel}", daemon=True)
        self._watchdog.start()

    def shutdown(self) -> None:
        self._stop.set()
        if self._watchdog is not None:
            self._watchdog.join(timeout=2.0)
            self._watchdog = None
        if self.network is not None:
            for drive in self.drives.values():
                drive.node.nmt.stop_heartbeat()
            self.network.disconnect()
            self.network = None

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        now = time.monotonic()
        with self.lock:
            for drive in self.drives.values():
                drive.on_sync(now)

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        command, node_id = data[0], data[1]
        with self.lock:
            for drive in self.drives.values():
                if drive.connected and node_id in (0, drive.node.id):
                    drive.on_nmt(command)

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        now = time.monotonic()
        with self.lock:
            for drive in self.drives.values():
                if drive.connected:
                    drive.on_heartbeat(can_id - 0x700, now)

    def _watch(self) -> None:
        """Heartbeat consumers, and the drives' own clock whenever SYNC has stopped reaching them."""
        while not self._stop.wait(WATCHDOG_PERIOD_S):
            now = time.monotonic()
            with self.lock:
                for drive in self.drives.values():
                    drive.check_heartbeat(now)
                    period_s = drive.parameter(cia402.COMMUNICATION_CYCLE_PERIOD) / 1e6
                    sync_missing = now - drive.last_sync_s > max(3.0 * period_s, 2.0 * WATCHDOG_PERIOD_S)
                    if sync_missing and drive.runs_on_own_clock():
                        drive.advance(now - drive.last_step_s, synchronous=False)
                        drive.last_step_s = now
                    elif not drive.synchronous:
                        drive.last_step_s = now  # idle without SYNC: its clock starts from now when enabled
                    drive.send_event_tpdos(now)

    def inject_bus_off(self) -> None:
        """What a CAN controller reports when it goes bus-off: an error frame of class BUSOFF."""
        assert self.network is not None and self.network.bus is not None
        self.network.bus.send(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, dlc=8, data=bytes(8)))
