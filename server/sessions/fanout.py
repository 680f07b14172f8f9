"""The web side's telemetry fan-out to WebSocket clients."""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import logging
from typing import TYPE_CHECKING

from server.jsonable import to_jsonable

if TYPE_CHECKING:
    from server.robotd.interfaces import RobotLink

logger = logging.getLogger(__name__)


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
