"""What the worker publishes every tick: supervisor states, stop reasons, limit codes and the record dtypes.

One `TELEMETRY_DTYPE` record per tick goes into the shared-memory ring (drained by the service into the
session log) and, behind the seqlock, is also the latest state. Fields are SI; `state`, `stop_reason`
and `limit_code` hold the integer codes of the enums below.
"""

from __future__ import annotations

import enum
import json
from typing import Any

import numpy as np

from core.plan.limits import LimitCode  # the record's `limit_code` holds these numbers
from server.hal.base import AXIS_COUNT, HalState


class SupervisorState(enum.IntEnum):
    IDLE = 0
    READY = 1
    RUNNING = 2
    PAUSED = 3
    STOPPING = 4
    STOPPED = 5
    ESTOP = 6
    FAULT = 7

    @property
    def label(self) -> str:
        return self.name.lower()


class StopReason(enum.IntEnum):
    NONE = 0
    OPERATOR = 1  # stop command
    COMPLETED = 2  # prescription finished
    EMERGENCY_STOP = 3
    WATCHDOG = 4  # no heartbeat from the service
    SERVICE_LOST = 5  # the command pipe closed: the service process is gone
    LATE_TICKS = 6
    LIMIT = 7
    FALL = 8
    TRACKING_ERROR = 9
    HAL_FAULT = 10
    INTERNAL_ERROR = 11
    RECORDING_FAILED = 12  # the daemon could not write the run's journal (disk full, I/O error)
    WORKER_LOST = 13  # a fresh worker shows that its predecessor died; the drives stayed off
    DAEMON_LOST = 14  # a fresh daemon's worker shows that the daemon died during a run


HAL_STATE_CODES = {state: code for code, state in enumerate(HalState)}
HAL_STATES_BY_CODE = dict(enumerate(HalState))

# 8-byte fields first so that every array field stays aligned (the compiled kernels write into them).
TELEMETRY_DTYPE = np.dtype(
    [
        ("tick", np.int64),
        ("time_s", np.float64),  # monotonic time of this tick's start since the worker started
        ("session_time_s", np.float64),  # the same clock, since the session's start (0 outside a session)
        ("utc_s", np.float64),  # wall clock, POSIX seconds
        ("segment_time_s", np.float64),
        ("cue_specific_force_m_s2", np.float64, (3,)),
        ("cue_angular_velocity_rad_s", np.float64, (3,)),
        ("stance_pose", np.float64, (6,)),  # commanded, relative to neutral
        ("measured_stance_pose", np.float64, (6,)),  # FK of the measured right-robot sliders
        ("slider_command_m", np.float64, (AXIS_COUNT,)),
        ("slider_position_m", np.float64, (AXIS_COUNT,)),
        ("slider_velocity_m_s", np.float64, (AXIS_COUNT,)),
        ("predicted_force_n", np.float64, (AXIS_COUNT,)),  # inverse dynamics of the command
        ("drive_force_n", np.float64, (AXIS_COUNT,)),
        ("plate_force_z_n", np.float64, (2,)),
        ("plate_cop_m", np.float64, (2, 2)),
        ("harness_load_n", np.float64),
        ("tracking_error_m", np.float64),  # max |slider command − measured position|
        ("tick_compute_us", np.float32),
        ("lateness_us", np.float32),
        ("deadline_misses", np.uint32),  # cumulative late ticks
        ("limit_hits", np.uint32),  # cumulative
        ("plan_index", np.int32),  # the checked plan's sample played in this tick; -1 off the plan (transitions)
        ("segment", np.int16),  # prescription segment being played, -1 for none
        ("fk_iterations", np.int16),
        ("late_streak", np.uint16),  # consecutive late ticks
        ("skipped_ticks", np.uint16),  # control periods skipped just before this sample (0: on time)
        ("drive_state", np.int8, (AXIS_COUNT,)),
        ("state", np.uint8),  # SupervisorState
        ("hal_state", np.uint8),  # HAL_STATE_CODES
        ("stop_reason", np.uint8),  # StopReason of the latest stop
        ("estop_latched", np.uint8),
        ("limit_code", np.uint8),  # LimitCode of the latest hit
        ("fall_detected", np.uint8),
        ("fall_detection_unavailable", np.uint8),  # the backend reads no force plates or harness load cell
    ]
)

EVENT_DETAILS_BYTES = 480
EVENT_DTYPE = np.dtype(
    [
        ("tick", np.int64),
        ("tick_time_s", np.float64),
        ("utc_s", np.float64),
        ("kind", "S40"),
        ("detector", "S40"),
        ("details", f"S{EVENT_DETAILS_BYTES}"),  # JSON
    ]
)


def encode_event(record: np.ndarray, kind: str, details: dict[str, Any], detector: str | None = None) -> None:
    """Fill one EVENT_DTYPE record in place; details that do not fit are cut down, never dropped."""
    text = json.dumps(details, default=float).encode()
    if len(text) > EVENT_DETAILS_BYTES:
        text = json.dumps({"truncated": text[: EVENT_DETAILS_BYTES - 40].decode(errors="ignore")}).encode()
    record["kind"] = kind.encode()[:40]
    record["detector"] = (detector or "").encode()[:40]
    record["details"] = text


def decode_events(records: np.ndarray) -> list[dict[str, Any]]:
    """EVENT_DTYPE records → the dicts the service stores: kind, tick, tick_time_s, utc, detector?, details."""
    import datetime as dt

    events = []
    for record in records:
        event: dict[str, Any] = {
            "kind": record["kind"].decode(),
            "tick": int(record["tick"]),
            "tick_time_s": float(record["tick_time_s"]),
            "utc": dt.datetime.fromtimestamp(float(record["utc_s"]), dt.UTC).isoformat(),
            "details": json.loads(record["details"].decode() or "{}"),
        }
        if record["detector"]:
            event["detector"] = record["detector"].decode()
        events.append(event)
    return events


def state_dict(record: np.ndarray) -> dict[str, Any]:
    """One telemetry record as the plain dict `WorkerClient.latest_state()` returns."""
    result: dict[str, Any] = {}
    for name in TELEMETRY_DTYPE.names or ():
        value = record[name]
        result[name] = value.tolist() if isinstance(value, np.ndarray) else value.item()
    result["state"] = SupervisorState(result["state"]).label
    result["hal_state"] = HAL_STATES_BY_CODE[result["hal_state"]].value
    result["stop_reason"] = StopReason(result["stop_reason"]).name.lower()
    result["limit_code"] = LimitCode(result["limit_code"]).label
    result["estop_latched"] = bool(result["estop_latched"])
    result["fall_detected"] = bool(result["fall_detected"])
    result["fall_detection_unavailable"] = bool(result["fall_detection_unavailable"])
    return result
