"""Session-log helpers shared by the robot daemon's recorder (server.robotd.daemon) and the web side:
which worker events end a run and with which outcome, event time stamps, telemetry chunk encoding; and
the web side's telemetry fan-out to WebSocket clients.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import io
import json
import logging
from typing import TYPE_CHECKING, Any

import numpy as np

from server.jsonable import to_jsonable

if TYPE_CHECKING:
    from server.sessions.worker import RobotLink

logger = logging.getLogger(__name__)

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


def encode_chunk(records: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, records, allow_pickle=False)
    return buffer.getvalue()


def decode_chunk(data: bytes) -> np.ndarray:
    return np.load(io.BytesIO(data), allow_pickle=False)


class TelemetryFanout:
    """The web side's telemetry frames: about 30 per second, built once from the robot link's state
    (shared memory) whatever the number of WebSocket clients, so watching never adds load to the robot."""

    def __init__(self, robot: RobotLink, telemetry_rate_hz: float = 30.0) -> None:
        self.robot = robot
        self.frame_period_s = 1.0 / telemetry_rate_hz
        self._subscribers: set[asyncio.Queue[str]] = set()

    def frame(self) -> str:
        parts = self.robot.frame()
        return json.dumps(to_jsonable({"type": "telemetry", "utc": dt.datetime.now(dt.UTC).isoformat(), **parts}))

    def subscribe(self) -> asyncio.Queue[str]:
        queue: asyncio.Queue[str] = asyncio.Queue(maxsize=1)
        self._subscribers.add(queue)
        return queue

    def unsubscribe(self, queue: asyncio.Queue[str]) -> None:
        self._subscribers.discard(queue)

    @property
    def subscriber_count(self) -> int:
        return len(self._subscribers)

    def broadcast(self, frame: str) -> None:
        """Latest frame wins: a slow client skips frames instead of holding back the others."""
        for queue in self._subscribers:
            if queue.full():
                queue.get_nowait()
            queue.put_nowait(frame)

    async def run_forever(self) -> None:
        loop = asyncio.get_running_loop()
        next_frame = loop.time()
        while True:
            try:
                if self._subscribers:
                    self.broadcast(await asyncio.to_thread(self.frame))
            except Exception:
                logger.exception("telemetry fan-out: one frame failed")
            # Absolute frame times, so that sleep overshoot does not add up and lower the frame rate;
            # after falling more than a frame behind, restart the schedule rather than burst.
            next_frame += self.frame_period_s
            if next_frame < loop.time() - self.frame_period_s:
                next_frame = loop.time()
            await asyncio.sleep(max(0.0, next_frame - loop.time()))
