"""The `canopen` HAL backend: twelve CiA 402 servo drives over CANopen (python-canopen + python-can).

configure(): check each drive type's EDS, NMT reset communication and wait for every boot-up, check
each drive's identity (0x1018), profile (0x1000) and supported modes (0x6502: CSP and homing), write
its parameters and PDO mapping over SDO, NMT start, then produce the master heartbeat and consume the
drives'. home(): CiA 402 homing (0x6098) on every axis. activate(): Cyclic Synchronous Position.

Each tick, write() sends every axis's RPDO (controlword, target, mode) and then one SYNC; the drives
latch on SYNC and answer with their TPDOs, which read() picks up without waiting. read() also sends
the cycle when nothing was written (outside ACTIVE), so drives stay supervised, and it is where every
bus event turns into a HAL fault with a controlled quick stop: a drive fault, a heartbeat timeout,
a rebooted drive, bus-off. Events are logged and kept for `drain_events()`.
"""

from __future__ import annotations

import collections
import datetime as dt
import logging
import math
import threading
import time
from collections.abc import Callable, Iterable
from typing import Any, cast

import can
import canopen
import numpy as np
from canopen.sdo import SdoAbortedError, SdoArray, SdoCommunicationError, SdoRecord

from core.robot import TwinRobot
from server.hal.base import AXIS_COUNT, DriveState, HalCommand, HalError, HalReading, HalState, HardwareInterface
from server.hal.canopen import cia402
from server.hal.canopen.pdo import (
    CAN_ERR_BUSOFF,
    RPDO_COB_BASE,
    RPDO_LAYOUT,
    SYNC_COB_ID,
    TPDO_COB_BASE,
    TPDO_LAYOUT,
    TRANSMISSION_TYPE_EVERY_SYNC,
    PdoCodec,
    cycle_bus_bits,
    layout_codecs,
)
from server.hal.canopen.simulated_drive import SimulatedDriveRack
from server.hal.canopen.units import (
    AxisScaling,
    DriveConfiguration,
    DriveConfigurationError,
    DriveType,
    load_drive_configuration,
)

logger = logging.getLogger(__name__)

NMT_RESET_COMMUNICATION, NMT_START = 0x82, 0x01
NMT_STATE_OPERATIONAL = 0x05
BOOT_TIMEOUT_S = 2.0
SDO_TIMEOUT_S = 1.0  # python-canopen's 0.3 s default is too short for a loaded host running simulated drives
STATE_CHANGE_TIMEOUT_S = 1.0
MAX_BUS_LOAD = 0.7  # of the bitrate, for one control cycle's frames on a real bus
REQUIRED_MODES = (cia402.OperationMode.CYCLIC_SYNCHRONOUS_POSITION, cia402.OperationMode.HOMING)
REQUIRED_OBJECTS = (
    cia402.DEVICE_TYPE,
    cia402.COMMUNICATION_CYCLE_PERIOD,
    cia402.CONSUMER_HEARTBEAT_TIME,
    cia402.PRODUCER_HEARTBEAT_TIME,
    cia402.IDENTITY,
    0x1400,
    0x1600,
    0x1800,
    0x1801,
    0x1A00,
    0x1A01,
    cia402.ABORT_CONNECTION_OPTION_CODE,
    cia402.QUICK_STOP_OPTION_CODE,
    cia402.FAULT_REACTION_OPTION_CODE,
    cia402.FOLLOWING_ERROR_WINDOW,
    cia402.FOLLOWING_ERROR_TIMEOUT,
    cia402.HOME_OFFSET,
    cia402.QUICK_STOP_DECELERATION,
    cia402.HOMING_METHOD,
    cia402.HOMING_SPEEDS,
    cia402.HOMING_ACCELERATION,
    cia402.SUPPORTED_DRIVE_MODES,
)
# In the cyclic path the master never resets a fault or re-enables a drive on its own: those
# transitions are allowed only inside the lifecycle call that asks for them.
FAULT_RESET, ENABLE_OPERATION, QUICK_STOP_ENABLE = 15, 4, 16
CYCLIC_FORBIDDEN = frozenset({FAULT_RESET, ENABLE_OPERATION, QUICK_STOP_ENABLE})
# 0x605A the master writes into every drive, and plans its controlword paths under: a quick stop ramps
# down and holds, powered, in QUICK STOP ACTIVE until the master disables the drive.
QUICK_STOP_OPTION = cia402.QuickStopOption.QUICK_STOP_RAMP_AND_STAY
QUIET_EVENTS = frozenset({"homed", "fault_reset", "bus_recovered"})
HOLD_CONTROLWORDS = np.array([cia402.HOLD_CONTROLWORD[DriveState(s)] for s in range(len(DriveState))], dtype=np.int64)


def check_eds(drive_type: DriveType) -> canopen.ObjectDictionary:
    """Load a drive type's EDS and refuse it unless it holds every object this backend uses."""
    field = f"drive_types.{drive_type.name}.eds"
    try:
        od = canopen.import_od(str(drive_type.eds_path))
    except Exception as error:  # the EDS parser raises anything from KeyError to ValueError
        raise DriveConfigurationError(
            field, str(drive_type.eds_path), f"not a readable EDS/DCF file: {error}"
        ) from error
    for index in REQUIRED_OBJECTS:
        if index not in od:
            raise DriveConfigurationError(field, drive_type.eds_path.name, f"lacks object 0x{index:04X}")
    for layout in (*RPDO_LAYOUT, *TPDO_LAYOUT):
        for index in layout:
            variable = od.get_variable(index) if index in od else None
            if variable is None or not variable.pdo_mappable:
                raise DriveConfigurationError(
                    field, drive_type.eds_path.name, f"object 0x{index:04X} is not PDO-mappable"
                )
    return od


def interpolation_period(control_period_s: float) -> tuple[int, int]:
    """0x60C2 (value, index) with value · 10^index s equal to the control period."""
    for index in (-3, -4, -5, -6):
        value = control_period_s * 10.0**-index
        if abs(value - round(value)) < 1e-6 and 1 <= round(value) <= 255:
            return round(value), index
    raise DriveConfigurationError("control_period_s", control_period_s, "not expressible as 0x60C2 value·10^index s")


class _BusMonitor(can.Listener):
    """Watches the raw bus for what python-canopen drops: error frames (bus-off) and receive errors."""

    def __init__(self) -> None:
        self.bus_off = False
        self.receive_error: Exception | None = None

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame and msg.arbitration_id & CAN_ERR_BUSOFF:
            self.bus_off = True

    def on_error(self, exc: Exception) -> None:
        self.receive_error = exc


class CanopenHal(HardwareInterface):
    """Twelve CiA 402 drives on one CAN bus, in Cyclic Synchronous Position mode at the control period."""

    def __init__(
        self,
        twin: TwinRobot,
        control_period_s: float,
        *,
        interface: str,
        channel: str,
        configuration: DriveConfiguration | None = None,
        bitrate: int | None = None,
        simulated_drives: SimulatedDriveRack | None = None,
    ) -> None:
        super().__init__(twin, control_period_s)
        self.interface = interface
        self.channel = channel
        self.bitrate = bitrate
        self.configuration = configuration if configuration is not None else load_drive_configuration()
        self.scaling = AxisScaling(self.configuration, twin)
        self.simulated_drives = simulated_drives
        self.node_ids = self.configuration.node_ids
        self.network: canopen.Network | None = None
        self._bus_monitor = _BusMonitor()
        self._heartbeat_task: Any = None
        self._events: collections.deque[dict[str, Any]] = collections.deque(maxlen=10_000)
        self._rpdo_codecs: list[PdoCodec] = []
        self.transition_log: list[tuple[int, int, DriveState, DriveState]] = []  # (sync, axis, from, to)
        # Latest TPDO values, written by the receive thread.
        self.statuswords = np.zeros(AXIS_COUNT, dtype=np.int64)
        self.position_counts = np.zeros(AXIS_COUNT, dtype=np.int64)
        self.torque_per_mille = np.zeros(AXIS_COUNT, dtype=np.int64)
        self.velocity_counts_s = np.zeros(AXIS_COUNT, dtype=np.int64)
        self.error_codes = np.zeros(AXIS_COUNT, dtype=np.int64)
        self.mode_display = np.zeros(AXIS_COUNT, dtype=np.int64)
        self.heartbeat_seen_s = np.full(AXIS_COUNT, math.nan)
        self._rebooted = np.zeros(AXIS_COUNT, dtype=bool)
        # What the master sends.
        self.controlwords = np.zeros(AXIS_COUNT, dtype=np.int64)
        self.target_counts = np.zeros(AXIS_COUNT, dtype=np.int64)
        self.modes = np.zeros(AXIS_COUNT, dtype=np.int64)
        self.target_states = [DriveState.SWITCH_ON_DISABLED] * AXIS_COUNT
        self._homing_start = np.zeros(AXIS_COUNT, dtype=bool)
        self._forbidden_transitions = CYCLIC_FORBIDDEN
        # Decoded per read.
        self.drive_states = np.zeros(AXIS_COUNT, dtype=np.int8)
        self._previous_states = np.zeros(AXIS_COUNT, dtype=np.int8)
        self.homed = np.zeros(AXIS_COUNT, dtype=bool)
        self._positions_m = np.zeros(AXIS_COUNT)
        self._reported_faults = np.zeros(AXIS_COUNT, dtype=bool)
        self._reported_silent = np.zeros(AXIS_COUNT, dtype=bool)
        self._bus_failure_reported = False
        self._expect_operation_enabled = False  # true while ACTIVE outside lifecycle calls
        self.sync_count = 0
        self._cycle_sent_since_read = False
        self._feedback_lock = threading.Lock()
        self._feedback_pending = 0
        self._feedback_done = threading.Event()
        self._heartbeat_timeout_s = self.configuration.heartbeat_timeout_ms / 1e3

    # --- events -------------------------------------------------------------------------------------

    def _event(self, kind: str, message: str, **details: Any) -> None:
        event = {
            "kind": kind,
            "utc": dt.datetime.now(dt.UTC).isoformat(),
            "monotonic_s": time.monotonic(),
            "sync_count": self.sync_count,
            "message": message,
            "details": details,
        }
        self._events.append(event)
        logger.log(logging.INFO if kind in QUIET_EVENTS else logging.WARNING, "canopen %s: %s", kind, message)

    def drain_events(self) -> list[dict[str, Any]]:
        """Events since the last drain, oldest first: faults, heartbeat losses, bus-off, EMCYs, stops."""
        drained = []
        while self._events:
            drained.append(self._events.popleft())
        return drained

    def axis_label(self, axis: int | np.integer) -> str:
        return f"{self.axis_name(int(axis))} (node {self.node_ids[int(axis)]})"

    # --- configure ----------------------------------------------------------------------------------

    def _on_configure(self) -> None:
        drive_types = {axis.drive_type.name: axis.drive_type for axis in self.configuration.axes}
        dictionaries = {name: check_eds(drive_type) for name, drive_type in drive_types.items()}
        self._check_bus_load(next(iter(dictionaries.values())))
        try:
            if self.simulated_drives is not None:
                self.simulated_drives.start()
            self._open_network()
            self._boot_all()
            for axis in range(AXIS_COUNT):
                self._check_identity(axis, dictionaries[self.configuration.axes[axis].drive_type.name])
            for axis in range(AXIS_COUNT):
                self._write_parameters(axis)
                self._map_pdos(axis)
            self._start_operation()
        except BaseException:
            self._close()
            raise

    def _check_bus_load(self, od: canopen.ObjectDictionary) -> None:
        if self.bitrate is None:
            return  # virtual buses and vcan have no bitrate
        bits = cycle_bus_bits(AXIS_COUNT, od)
        load = bits / (self.bitrate * self.control_period_s)
        if load > MAX_BUS_LOAD:
            raise DriveConfigurationError(
                "control_period_s",
                self.control_period_s,
                f"{AXIS_COUNT} axes need {bits} bits per cycle, {load:.0%} of a {self.bitrate} bit/s bus "
                f"(limit {MAX_BUS_LOAD:.0%}); the shortest period is "
                f"{bits / (MAX_BUS_LOAD * self.bitrate) * 1e3:.2f} ms",
            )

    def _open_network(self) -> None:
        network = canopen.Network()
        network.NOTIFIER_CYCLE = 0.05  # lets shutdown join the receive thread quickly
        cast(list[can.Listener], network.listeners).append(self._bus_monitor)
        for axis, drive in enumerate(self.configuration.axes):
            node = canopen.RemoteNode(drive.node_id, str(drive.drive_type.eds_path))
            node.sdo.RESPONSE_TIMEOUT = SDO_TIMEOUT_S
            network.add_node(node)
            node.nmt.add_heartbeat_callback(self._heartbeat_callback(axis))
            node.emcy.add_callback(self._emcy_callback(axis))
        kwargs: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.bitrate is not None:
            kwargs["bitrate"] = self.bitrate
        try:
            network.connect(**kwargs)
        except (can.CanError, OSError, ValueError) as error:
            raise DriveConfigurationError(
                "can_channel", f"{self.interface}:{self.channel}", f"cannot open: {error}"
            ) from error
        self.network = network

    def _heartbeat_callback(self, axis: int) -> Callable[[int], None]:
        def on_heartbeat(nmt_state: int) -> None:
            self.heartbeat_seen_s[axis] = time.monotonic()
            if nmt_state == 0:
                self._rebooted[axis] = True

        return on_heartbeat

    def _emcy_callback(self, axis: int) -> Callable[[Any], None]:
        def on_emcy(entry: Any) -> None:
            self._event(
                "drive_emcy",
                f"{self.axis_label(axis)}: EMCY {cia402.describe_error_code(entry.code)}",
                axis=axis,
                node_id=self.node_ids[axis],
                error_code=entry.code,
            )

        return on_emcy

    def _boot_all(self) -> None:
        """NMT reset communication to every node, then wait for each boot-up message."""
        assert self.network is not None
        self._rebooted[:] = False
        self.network.send_message(0, bytes([NMT_RESET_COMMUNICATION, 0]))
        deadline = time.monotonic() + BOOT_TIMEOUT_S
        while not self._rebooted.all() and time.monotonic() < deadline:
            time.sleep(0.002)
        if not self._rebooted.all():
            silent = [self.axis_label(a) for a in np.flatnonzero(~self._rebooted)]
            raise DriveConfigurationError("node_id", silent, f"no boot-up within {BOOT_TIMEOUT_S} s after NMT reset")
        self._rebooted[:] = False

    def _sdo_read(self, axis: int, index: int, subindex: int = 0) -> int:
        assert self.network is not None
        node = self.network[self.node_ids[axis]]
        try:
            entry = node.sdo[index]
            return int((entry[subindex] if isinstance(entry, SdoRecord | SdoArray) else entry).raw)
        except (SdoAbortedError, SdoCommunicationError) as error:
            raise DriveConfigurationError(
                f"{self.axis_label(axis)} 0x{index:04X}:{subindex:02X}", "<SDO upload>", str(error)
            ) from error

    def _sdo_write(self, axis: int, index: int, subindex: int, value: int, field: str) -> None:
        assert self.network is not None
        node = self.network[self.node_ids[axis]]
        try:
            entry = node.sdo[index]
            (entry[subindex] if isinstance(entry, SdoRecord | SdoArray) else entry).raw = value
        except (SdoAbortedError, SdoCommunicationError) as error:
            raise DriveConfigurationError(
                field, value, f"{self.axis_label(axis)} refused 0x{index:04X}:{subindex:02X}: {error}"
            ) from error

    def _check_identity(self, axis: int, od: canopen.ObjectDictionary) -> None:
        """The drive on the bus must be the drive type the EDS describes, and support CSP and homing."""
        drive_type = self.configuration.axes[axis].drive_type
        info = od.device_information
        field = f"drive_types.{drive_type.name}.eds"
        expected = {1: info.vendor_number, 2: info.product_number}
        for subindex, name in ((1, "vendor-ID"), (2, "product code")):
            actual = self._sdo_read(axis, cia402.IDENTITY, subindex)
            if expected[subindex] is not None and actual != expected[subindex]:
                raise DriveConfigurationError(
                    field,
                    drive_type.eds_path.name,
                    f"{self.axis_label(axis)} reports {name} 0x{actual:08X} (0x1018:{subindex:02X}), "
                    f"the EDS describes 0x{expected[subindex]:08X}: wrong EDS for this drive",
                )
        revision = self._sdo_read(axis, cia402.IDENTITY, 3)
        if info.revision_number is not None and revision >> 16 != info.revision_number >> 16:
            raise DriveConfigurationError(
                field,
                drive_type.eds_path.name,
                f"{self.axis_label(axis)} has major revision {revision >> 16}, the EDS {info.revision_number >> 16}",
            )
        device_type = self._sdo_read(axis, cia402.DEVICE_TYPE)
        if device_type & 0xFFFF != cia402.DRIVE_PROFILE_NUMBER:
            raise DriveConfigurationError(
                f"{self.axis_label(axis)} 0x1000", f"0x{device_type:08X}", "not a CiA 402 drive (profile 402)"
            )
        supported = self._sdo_read(axis, cia402.SUPPORTED_DRIVE_MODES)
        for mode in REQUIRED_MODES:
            if not supported & mode.supported_modes_bit:
                raise DriveConfigurationError(
                    f"{self.axis_label(axis)} 0x6502 supported drive modes",
                    f"0x{supported:08X}",
                    f"mode {mode.value} ({mode.name.replace('_', ' ').lower()}) is required and not supported",
                )

    def _write_parameters(self, axis: int) -> None:
        drive = self.configuration.axes[axis]
        kind = drive.drive_type
        section = f"drive_types.{kind.name}"
        period_value, period_index = interpolation_period(self.control_period_s)
        master = self.configuration
        writes: list[tuple[int, int, int, str]] = [
            (cia402.COMMUNICATION_CYCLE_PERIOD, 0, round(self.control_period_s * 1e6), "control_period_s"),
            (cia402.INTERPOLATION_TIME_PERIOD, 1, period_value, "control_period_s"),
            (cia402.INTERPOLATION_TIME_PERIOD, 2, period_index, "control_period_s"),
            (cia402.QUICK_STOP_OPTION_CODE, 0, QUICK_STOP_OPTION, "quick_stop_option"),
            (
                cia402.FAULT_REACTION_OPTION_CODE,
                0,
                cia402.QuickStopOption.QUICK_STOP_RAMP_THEN_DISABLE,
                "fault_reaction",
            ),
            (cia402.ABORT_CONNECTION_OPTION_CODE, 0, cia402.AbortConnectionOption.FAULT, "abort_connection_option"),
            (
                cia402.QUICK_STOP_DECELERATION,
                0,
                kind.counts(kind.quick_stop_deceleration_mm_s2),
                f"{section}.quick_stop_deceleration_mm_s2",
            ),
            (cia402.HOMING_METHOD, 0, kind.homing_method, f"{section}.homing_method"),
            (
                cia402.HOMING_SPEEDS,
                1,
                kind.counts(kind.homing_switch_speed_mm_s),
                f"{section}.homing_switch_speed_mm_s",
            ),
            (cia402.HOMING_SPEEDS, 2, kind.counts(kind.homing_zero_speed_mm_s), f"{section}.homing_zero_speed_mm_s"),
            (
                cia402.HOMING_ACCELERATION,
                0,
                kind.counts(kind.homing_acceleration_mm_s2),
                f"{section}.homing_acceleration_mm_s2",
            ),
            (cia402.HOME_OFFSET, 0, 0, "home_offset"),
            (
                cia402.FOLLOWING_ERROR_WINDOW,
                0,
                kind.counts(kind.following_error_window_mm),
                f"{section}.following_error_window_mm",
            ),
            (
                cia402.FOLLOWING_ERROR_TIMEOUT,
                0,
                kind.following_error_timeout_ms,
                f"{section}.following_error_timeout_ms",
            ),
            (
                cia402.CONSUMER_HEARTBEAT_TIME,
                1,
                master.master_node_id << 16 | master.heartbeat_timeout_ms,
                "heartbeat_timeout_ms",
            ),
            (cia402.PRODUCER_HEARTBEAT_TIME, 0, master.heartbeat_period_ms, "heartbeat_period_ms"),
        ]
        assert self.network is not None
        od = self.network[drive.node_id].object_dictionary
        for index, subindex, value, field in writes:
            if index in od:  # 0x60C2 is optional in CiA 402
                self._sdo_write(axis, index, subindex, value, field)

    def _map_pdos(self, axis: int) -> None:
        """Write the PDO layout into the drive (CiA 301 §7.4.7 sequence, done by python-canopen's save())."""
        assert self.network is not None
        node_id = self.node_ids[axis]
        node = self.network[node_id]
        for maps, layout, bases in ((node.rpdo, RPDO_LAYOUT, RPDO_COB_BASE), (node.tpdo, TPDO_LAYOUT, TPDO_COB_BASE)):
            assert maps.map is not None
            for number, pdo_map in maps.map.items():
                indices = layout[number - 1] if number <= len(layout) else ()
                pdo_map.clear()
                for index in indices:
                    pdo_map.add_variable(index)
                pdo_map.cob_id = bases[number - 1] + node_id
                pdo_map.trans_type = TRANSMISSION_TYPE_EVERY_SYNC
                pdo_map.enabled = bool(indices)
                try:
                    pdo_map.save()
                except (SdoAbortedError, SdoCommunicationError) as error:
                    raise DriveConfigurationError(
                        "pdo_mapping", f"0x{pdo_map.cob_id:03X}", f"{self.axis_label(axis)} refused: {error}"
                    ) from error
                if pdo_map.enabled:
                    # Decoded by the master's own callback below; canopen's per-map one only adds latency.
                    self.network.unsubscribe(pdo_map.cob_id, pdo_map.on_message)

    def _start_operation(self) -> None:
        assert self.network is not None
        od = self.network[self.node_ids[0]].object_dictionary
        self._rpdo_codecs = [layout_codecs(RPDO_LAYOUT, RPDO_COB_BASE, node_id, od)[0] for node_id in self.node_ids]
        for axis, node_id in enumerate(self.node_ids):
            status, motion = layout_codecs(TPDO_LAYOUT, TPDO_COB_BASE, node_id, od)
            self.network.subscribe(status.cob_id, self._status_tpdo(axis, status))
            self.network.subscribe(motion.cob_id, self._motion_tpdo(axis, motion))
        self._start_heartbeat()
        self.network.send_message(0, bytes([NMT_START, 0]))
        self.target_states = [DriveState.SWITCH_ON_DISABLED] * AXIS_COUNT
        self.modes[:] = cia402.OperationMode.CYCLIC_SYNCHRONOUS_POSITION
        self.homed[:] = False
        # First cycles: every drive must answer; one found in FAULT (from an earlier session) is reset.
        self._run_cycles(
            lambda: self._all_in({DriveState.SWITCH_ON_DISABLED}), "configure", allow=frozenset({FAULT_RESET})
        )
        self._reported_faults[:] = False

    # --- TPDO reception (receive thread) ------------------------------------------------------------

    def _status_tpdo(self, axis: int, codec: PdoCodec) -> Callable[[int, bytearray, float], None]:
        unpack = codec.layout.unpack_from

        def on_status(can_id: int, data: bytearray, timestamp: float) -> None:
            self.statuswords[axis], self.position_counts[axis], self.torque_per_mille[axis] = unpack(data)
            self._count_feedback()

        return on_status

    def _motion_tpdo(self, axis: int, codec: PdoCodec) -> Callable[[int, bytearray, float], None]:
        unpack = codec.layout.unpack_from

        def on_motion(can_id: int, data: bytearray, timestamp: float) -> None:
            self.velocity_counts_s[axis], self.error_codes[axis], self.mode_display[axis] = unpack(data)
            self._count_feedback()

        return on_motion

    def _count_feedback(self) -> None:
        with self._feedback_lock:
            self._feedback_pending -= 1
            if self._feedback_pending == 0:
                self._feedback_done.set()

    def wait_for_feedback(self, timeout_s: float) -> bool:
        """Block until every TPDO of the last SYNC has arrived (for demos, tests and the benchmark)."""
        return self._feedback_done.wait(timeout_s)

    # --- the cycle ----------------------------------------------------------------------------------

    def _transmit_cycle(self) -> None:
        """Every axis's RPDO, then SYNC: the drives latch the set-points and answer with their TPDOs."""
        network = self.network
        if network is None or self._bus_failed():
            return
        self._compute_controlwords()
        with self._feedback_lock:
            self._feedback_pending = 2 * AXIS_COUNT
            self._feedback_done.clear()
        rows = zip(
            self._rpdo_codecs, self.controlwords.tolist(), self.target_counts.tolist(), self.modes.tolist(), strict=True
        )
        try:
            for codec, controlword, target, mode in rows:
                network.send_message(codec.cob_id, codec.layout.pack(controlword, target, mode))
            network.send_message(SYNC_COB_ID, b"")
        except (can.CanError, OSError) as error:
            self._bus_monitor.receive_error = error
            return
        self.sync_count += 1
        self._cycle_sent_since_read = True

    def _compute_controlwords(self) -> None:
        steady = not self._homing_start.any() and all(
            int(state) == target for state, target in zip(self.drive_states, self.target_states, strict=True)
        )
        if steady:  # every drive where it should be: the hold words, no path search
            np.take(HOLD_CONTROLWORDS, self.drive_states, out=self.controlwords)
            return
        for axis in range(AXIS_COUNT):
            state = DriveState(int(self.drive_states[axis]))
            target = self.target_states[axis]
            previous = int(self.controlwords[axis])
            word = cia402.HOLD_CONTROLWORD[state]
            if state != target:
                try:
                    step = cia402.transition_path(state, target, QUICK_STOP_OPTION)[0]
                except ValueError:
                    step = None
                if step is not None and step.number not in self._forbidden_transitions:
                    word = cia402.next_controlword(state, target, previous, QUICK_STOP_OPTION)
            if self._homing_start[axis] and state == DriveState.OPERATION_ENABLED:
                word |= cia402.CONTROLWORD_HOMING_START
            self.controlwords[axis] = word

    def _decode(self) -> None:
        cia402.states_from_statuswords(self.statuswords, self.drive_states)
        changed = np.flatnonzero(self.drive_states != self._previous_states)
        for axis in changed:
            self.transition_log.append(
                (
                    self.sync_count,
                    int(axis),
                    DriveState(int(self._previous_states[axis])),
                    DriveState(int(self.drive_states[axis])),
                )
            )
        self._previous_states[:] = self.drive_states

    def _bus_failed(self) -> bool:
        return self._bus_monitor.bus_off or self._bus_monitor.receive_error is not None

    def _health_fault(self) -> str | None:
        """Turn bus events into events; returns why the HAL must stop, or None."""
        reason = None
        if self._bus_failed() and not self._bus_failure_reported:
            self._bus_failure_reported = True
            self._stop_heartbeat()  # a bus-off controller cannot transmit: make that explicit
            cause = "bus-off" if self._bus_monitor.bus_off else f"bus error: {self._bus_monitor.receive_error}"
            reason = (
                f"CAN {cause} on {self.interface}:{self.channel}; the drives stop themselves when the master "
                f"heartbeat times out ({self.configuration.heartbeat_timeout_ms} ms)"
            )
            self._event("bus_off" if self._bus_monitor.bus_off else "bus_error", reason)
        now = time.monotonic()
        silent = (now - self.heartbeat_seen_s > self._heartbeat_timeout_s) & ~self._reported_silent
        for axis in np.flatnonzero(silent):
            self._reported_silent[axis] = True
            message = (
                f"{self.axis_label(axis)}: heartbeat lost for more than {self.configuration.heartbeat_timeout_ms} ms"
            )
            self._event("heartbeat_lost", message, axis=int(axis), node_id=self.node_ids[axis])
            reason = reason or message
        for axis in np.flatnonzero(self._rebooted):
            self._rebooted[axis] = False
            self.homed[axis] = False
            message = f"{self.axis_label(axis)}: drive rebooted (boot-up message); its homing is lost"
            self._event("drive_rebooted", message, axis=int(axis), node_id=self.node_ids[axis])
            reason = reason or message
        faulted = (self.drive_states == DriveState.FAULT) | (self.drive_states == DriveState.FAULT_REACTION_ACTIVE)
        for axis in np.flatnonzero(faulted & ~self._reported_faults):
            self._reported_faults[axis] = True
            message = f"{self.axis_label(axis)}: drive fault {cia402.describe_error_code(int(self.error_codes[axis]))}"
            self._event(
                "drive_fault",
                message,
                axis=int(axis),
                node_id=self.node_ids[axis],
                error_code=int(self.error_codes[axis]),
            )
            reason = reason or message
        if self._expect_operation_enabled and reason is None:
            left = np.flatnonzero(self.drive_states != DriveState.OPERATION_ENABLED)
            if left.size:
                first = int(left[0])
                reason = (
                    f"{self.axis_label(first)} left OPERATION_ENABLED: {DriveState(int(self.drive_states[first])).name}"
                )
                self._event("drive_left_operation", reason, axis=first, node_id=self.node_ids[first])
        return reason

    def _run_cycles(
        self,
        done: Callable[[], bool],
        action: str,
        *,
        timeout_s: float = STATE_CHANGE_TIMEOUT_S,
        allow: frozenset[int] = frozenset(),
    ) -> None:
        """Paced control cycles until `done()`, for lifecycle calls. A bus or drive fault stops everything."""
        if self.network is None:
            raise HalError(f"{action}: the CAN bus is closed")
        self._forbidden_transitions = CYCLIC_FORBIDDEN - set(allow)
        try:
            deadline = time.monotonic() + timeout_s
            next_tick = time.monotonic()
            while True:
                self._hold_targets_at_actual()
                self._transmit_cycle()
                self.wait_for_feedback(max(20 * self.control_period_s, 0.2))  # lock-step unless a drive is silent
                self._decode()
                fault = self._health_fault()
                # Configure and reset_fault clear faults, so only a lost bus or a silent drive stops them.
                tolerated = FAULT_RESET in allow and not (self._bus_failed() or self._reported_silent.any())
                if fault is not None and not tolerated:
                    self._stop_after_lifecycle_fault(fault)
                    raise HalError(f"{action}: {fault}")
                if done():
                    return
                if time.monotonic() > deadline:
                    raise HalError(f"{action}: timed out after {timeout_s:.1f} s; {self._describe_axes()}")
                next_tick += self.control_period_s
                time.sleep(max(0.0, next_tick - time.monotonic()))
        finally:
            self._forbidden_transitions = CYCLIC_FORBIDDEN
            self._cycle_sent_since_read = False  # those cycles' answers are read: the next read() sends

    def _stop_after_lifecycle_fault(self, reason: str) -> None:
        if self.state is HalState.CONFIGURED:
            self.fault(reason)
        else:
            self._on_quick_stop()

    def _hold_targets_at_actual(self) -> None:
        """Outside CSP motion the target follows the axis, so enabling never jumps."""
        self.target_counts[:] = self.position_counts

    def _all_in(self, states: set[DriveState]) -> bool:
        return all(DriveState(int(s)) in states for s in self.drive_states)

    def _describe_axes(self, axes: Iterable[int] | None = None) -> str:
        parts = []
        for axis in range(AXIS_COUNT) if axes is None else axes:
            state = DriveState(int(self.drive_states[axis]))
            text = f"{self.axis_label(axis)} {state.name}"
            if state in cia402.FAULT_STATES:
                text += f" ({cia402.describe_error_code(int(self.error_codes[axis]))})"
            parts.append(text)
        return "; ".join(parts)

    # --- lifecycle hooks ----------------------------------------------------------------------------

    def _on_home(self) -> None:
        self.modes[:] = cia402.OperationMode.HOMING
        self.target_states = [DriveState.OPERATION_ENABLED] * AXIS_COUNT
        self._run_cycles(self._all_enabled_in(cia402.OperationMode.HOMING), "home", allow=frozenset({ENABLE_OPERATION}))
        stroke = float(np.max(self.stroke_max_m - self.stroke_min_m)) * 1e3
        slowest = min(a.drive_type.homing_switch_speed_mm_s for a in self.configuration.axes)
        self._homing_start[:] = True
        started_at = self.sync_count
        try:
            self._run_cycles(
                lambda: self.sync_count > started_at + 1 and self._homing_finished(),
                "home",
                timeout_s=1.5 * stroke / slowest + 2.0,
                allow=frozenset({ENABLE_OPERATION}),
            )
        finally:
            self._homing_start[:] = False
        self.homed[:] = True
        self._event("homed", "every axis homed", method=[a.drive_type.homing_method for a in self.configuration.axes])
        self.target_states = [DriveState.SWITCH_ON_DISABLED] * AXIS_COUNT
        self._run_cycles(lambda: self._all_in({DriveState.SWITCH_ON_DISABLED}), "home")
        self.modes[:] = cia402.OperationMode.CYCLIC_SYNCHRONOUS_POSITION

    def _all_enabled_in(self, mode: cia402.OperationMode) -> Callable[[], bool]:
        return lambda: self._all_in({DriveState.OPERATION_ENABLED}) and bool(np.all(self.mode_display == mode))

    def _homing_finished(self) -> bool:
        failed = np.flatnonzero(self.statuswords & cia402.STATUSWORD_HOMING_ERROR)
        if failed.size:
            raise HalError(f"home: homing error on {self._describe_axes(failed)}")
        attained = cia402.STATUSWORD_HOMING_ATTAINED | cia402.STATUSWORD_TARGET_REACHED
        return bool(np.all(self.statuswords & attained == attained))

    def _on_activate(self) -> None:
        if not self.homed.all():
            raise HalError(
                "activate: not homed: "
                + ", ".join(self.axis_label(a) for a in np.flatnonzero(~self.homed))
                + "; call home()"
            )
        self.modes[:] = cia402.OperationMode.CYCLIC_SYNCHRONOUS_POSITION
        self.target_states = [DriveState.OPERATION_ENABLED] * AXIS_COUNT
        self._run_cycles(
            lambda: self._all_in({DriveState.OPERATION_ENABLED}), "activate", allow=frozenset({ENABLE_OPERATION})
        )
        refused = np.flatnonzero(self.mode_display != cia402.OperationMode.CYCLIC_SYNCHRONOUS_POSITION)
        if refused.size:
            self.target_states = [DriveState.SWITCH_ON_DISABLED] * AXIS_COUNT
            self._run_cycles(lambda: self._all_in({DriveState.SWITCH_ON_DISABLED}), "activate")
            raise HalError(f"activate: cyclic synchronous position refused by {self._describe_axes(refused)}")
        self._expect_operation_enabled = True

    def _on_deactivate(self) -> None:
        self._expect_operation_enabled = False
        self.target_states = [DriveState.SWITCH_ON_DISABLED] * AXIS_COUNT
        self._run_cycles(lambda: self._all_in({DriveState.SWITCH_ON_DISABLED}), "deactivate")

    def _on_quick_stop(self) -> None:
        """Quick stop (0x605A = 6: ramp at 0x6085, stay in QUICK STOP ACTIVE) on every powered axis."""
        self._expect_operation_enabled = False
        self.target_states = [cia402.quick_stop_target(DriveState(int(s))) for s in self.drive_states]
        self._homing_start[:] = False
        self._event("quick_stop", "quick stop commanded on every axis", reason=self.last_fault)
        self._transmit_cycle()

    def _on_disable(self) -> None:
        """After the quick-stop ramps end, remove power; bounded by the slowest ramp's duration."""
        if self.network is None or self._bus_failed():
            return
        decelerations = [a.drive_type.quick_stop_deceleration_mm_s2 / 1e3 for a in self.configuration.axes]
        ramp_s = 1.1 * self.twin.robot.limits.slider_velocity_max_m_s / min(decelerations) + 0.2
        try:
            self._run_cycles(self._stopped, "emergency stop", timeout_s=ramp_s)
        except HalError as error:
            self._event("stop_timeout", str(error))
        self.target_states = [
            DriveState(int(s))
            if s in (DriveState.FAULT, DriveState.FAULT_REACTION_ACTIVE)
            else DriveState.SWITCH_ON_DISABLED
            for s in self.drive_states
        ]
        try:
            self._run_cycles(lambda: self._all_in({DriveState.SWITCH_ON_DISABLED, DriveState.FAULT}), "disable")
        except HalError as error:
            self._event("disable_timeout", str(error))

    def _stopped(self) -> bool:
        moving = np.isin(self.drive_states, [DriveState.OPERATION_ENABLED, DriveState.FAULT_REACTION_ACTIVE])
        return not moving.any() and bool(np.all(self.velocity_counts_s == 0))

    def _on_reset_fault(self) -> None:
        if self.network is None:
            raise HalError("reset_fault: the bus is closed")
        if self._bus_failed():
            # Bus-off recovery is the controller's (socketcan restart-ms); the master resumes producing.
            self._bus_monitor.bus_off = False
            self._bus_monitor.receive_error = None
            self._bus_failure_reported = False
            self._start_heartbeat()
            self._event("bus_recovered", f"transmission resumed on {self.interface}:{self.channel}")
            time.sleep(2 * self.configuration.heartbeat_period_ms / 1e3)
        silent = np.flatnonzero(time.monotonic() - self.heartbeat_seen_s > self._heartbeat_timeout_s)
        if silent.size:
            raise HalError("reset_fault: no heartbeat from " + ", ".join(self.axis_label(a) for a in silent))
        self._reported_silent[:] = False
        self.target_states = [DriveState.SWITCH_ON_DISABLED] * AXIS_COUNT
        self._run_cycles(
            lambda: self._all_in({DriveState.SWITCH_ON_DISABLED}), "reset_fault", allow=frozenset({FAULT_RESET})
        )
        self._reported_faults[:] = False
        self._event("fault_reset", "every axis reset to SWITCH_ON_DISABLED")

    def _on_read(self, out: HalReading) -> None:
        if not self._cycle_sent_since_read:
            if self.state is not HalState.ACTIVE:
                self._hold_targets_at_actual()
            self._transmit_cycle()  # nothing written this tick: keep SYNC and the drives supervised
        self._cycle_sent_since_read = False
        self._decode()
        fault = self._health_fault()
        if fault is not None and self.state not in (HalState.FAULT, HalState.ESTOP):
            self.fault(fault)
        self.scaling.positions_from_counts(self.position_counts, out.positions_m)
        self.scaling.velocities_from_counts(self.velocity_counts_s, out.velocities_m_s)
        self.scaling.forces_from_torque(self.torque_per_mille, out.drive_forces_n)
        out.drive_states[:] = self.drive_states
        out.homed[:] = self.homed
        out.monotonic_ns = time.perf_counter_ns()
        out.hardware_time_s = self.sync_count * self.control_period_s

    def _on_write(self, command: HalCommand) -> None:
        self.scaling.counts_from_positions(command.positions_m, self.target_counts)
        self._transmit_cycle()

    def _measured_positions(self) -> np.ndarray:
        self.scaling.positions_from_counts(self.position_counts, self._positions_m)
        return self._positions_m

    def _on_shutdown(self) -> None:
        self._close()

    def shutdown(self) -> None:
        """Power off and close the bus; the bus and simulated drives close even if powering off fails."""
        try:
            super().shutdown()
        except HalError as error:
            # Drives that cannot be powered off stop themselves on the master heartbeat loss.
            self._event("shutdown_incomplete", f"shutdown: {error}")
        finally:
            self._close()
            self.state = HalState.UNCONFIGURED

    # --- bus --------------------------------------------------------------------------------------

    def _start_heartbeat(self) -> None:
        assert self.network is not None
        master = self.configuration
        self._heartbeat_task = self.network.send_periodic(
            0x700 + master.master_node_id, bytes([NMT_STATE_OPERATIONAL]), master.heartbeat_period_ms / 1e3
        )

    def _stop_heartbeat(self) -> None:
        if self._heartbeat_task is not None:
            self._heartbeat_task.stop()
            self._heartbeat_task = None

    def _close(self) -> None:
        """Stop producing, close the bus and any simulated drives this HAL owns; safe to call twice."""
        self._stop_heartbeat()
        if self.network is not None:
            try:
                self.network.disconnect()
            except (can.CanError, OSError) as error:
                logger.warning("closing %s:%s: %s", self.interface, self.channel, error)
            self.network = None
        if self.simulated_drives is not None:
            self.simulated_drives.shutdown()


def create_canopen_hal(
    twin: TwinRobot,
    control_period_s: float,
    interface: str,
    channel: str,
    *,
    configuration: DriveConfiguration | str | None = None,
    simulate: int = 0,
    bitrate: int | None = None,
) -> CanopenHal:
    """The backend `--backend canopen --can-interface … --can-channel …` selects.

    `simulate` > 0 adds that many simulated drives (nodes of the first axes) on the same channel,
    started at configure() and stopped at shutdown(): the whole robot on a `virtual` bus or `vcan`.
    """
    config = configuration if isinstance(configuration, DriveConfiguration) else load_drive_configuration(configuration)
    if not 0 <= simulate <= AXIS_COUNT:
        raise DriveConfigurationError("simulate", simulate, f"must be in [0, {AXIS_COUNT}] drives")
    rack = None
    if simulate:
        rack = SimulatedDriveRack(config, interface=interface, channel=channel, node_ids=config.node_ids[:simulate])
    return CanopenHal(
        twin,
        control_period_s,
        interface=interface,
        channel=channel,
        configuration=config,
        bitrate=bitrate,
        simulated_drives=rack,
    )
