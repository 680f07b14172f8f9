"""A run's records as the robot daemon's recorder (server.robotd.daemon) and crash recovery write them:
which worker events end a run and with which outcome, event rows and their time stamps, telemetry chunk
encoding (read back by exports and reports)."""

from __future__ import annotations

import datetime as dt
import io
from typing import Any

import numpy as np

from server.jsonable import to_jsonable
from server.robotd.models import SessionEvent

# Worker event kinds that end a run, and the outcome recorded for each (server/realtime: supervisor and
# pipeline events). A controlled stop carries its StopReason; the first terminal event of a run wins.
TERMINAL_EVENT_OUTCOMES = {
    "fall": "fall",
    "emergency_stop": "emergency_stop",
    "limit_hit": "limit_hit",
    "fault": "fault",
    "prescription_completed": "completed",
}
STOP_REASON_OUTCOMES = {"operator": "stopped", "completed": "completed", "limit": "limit_hit", "fall": "fall",
                        "emergency_stop": "emergency_stop", "watchdog": "interrupted",
                        "service_lost": "interrupted", "recording_failed": "interrupted"}  # fmt: skip


def terminal_outcome_of(kind: str, details: dict[str, Any]) -> str | None:
    """The run outcome a worker event implies, or None if the run goes on."""
    if kind == "controlled_stop":
        return STOP_REASON_OUTCOMES.get(str(details.get("reason")), "fault")
    return TERMINAL_EVENT_OUTCOMES.get(kind)


def event_utc(value: Any) -> dt.datetime:
    """The worker's UTC stamp (ISO 8601 string or POSIX seconds); now if it gave none."""
    if isinstance(value, str):
        parsed = dt.datetime.fromisoformat(value.replace("Z", "+00:00"))
        return parsed if parsed.tzinfo else parsed.replace(tzinfo=dt.UTC)
    if isinstance(value, int | float):
        return dt.datetime.fromtimestamp(float(value), dt.UTC)
    return dt.datetime.now(dt.UTC)


def event_row(run_id: int | None, event: dict[str, Any]) -> SessionEvent:
    """The database row of one worker or daemon event (the recorder's and the crash recovery's)."""
    tick, tick_time_s, user_id = event.get("tick"), event.get("tick_time_s"), event.get("user_id")
    return SessionEvent(
        run_id=run_id,
        kind=str(event.get("kind", "unknown"))[:32],
        tick=int(tick) if tick is not None else None,
        tick_time_s=float(tick_time_s) if tick_time_s is not None else None,
        utc=event_utc(event.get("utc")),
        detector=str(event["detector"])[:64] if event.get("detector") else None,
        details=to_jsonable(event.get("details") or {}),
        user_id=int(user_id) if user_id is not None else None,
    )


def encode_chunk(records: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, records, allow_pickle=False)
    return buffer.getvalue()


def decode_chunk(data: bytes) -> np.ndarray:
    return np.load(io.BytesIO(data), allow_pickle=False)
