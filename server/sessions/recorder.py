"""The session recorder: drains the real-time worker at the telemetry rate (about 30 Hz), fans each frame
out to every telemetry WebSocket, and writes the durable session log of the active run: the worker's
telemetry records in chunks (one `.npy` blob each, so they carry their own dtype) and its events.

It is the only consumer of `drain_telemetry()`/`drain_events()`, and it reads `latest_state()` once per
frame whatever the number of WebSocket clients, so watching a session never adds load to the worker.
A run ends when the worker reports a terminal event (fall, emergency stop, fault, limit hit, completion,
or a controlled stop with its reason) or the therapist stops it; recording continues for `tail_s`
afterwards to keep the aftermath.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import io
import json
import logging
import threading
import time
from typing import Any

import numpy as np
from sqlalchemy import select

from server.db import Database, write_transaction
from server.jsonable import to_jsonable
from server.scheduling.models import ScheduledSession
from server.sessions.models import SessionEvent, SessionRun, TelemetryChunk
from server.sessions.service import ACTIVE_STATES
from server.sessions.worker import WorkerControl

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
                        "emergency_stop": "emergency_stop"}  # fmt: skip


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


class SessionRecorder:
    def __init__(
        self,
        *,
        worker: WorkerControl,
        database: Database,
        telemetry_rate_hz: float = 30.0,
        flush_interval_s: float = 1.0,
        tail_s: float = 2.0,
    ) -> None:
        self.worker = worker
        self.database = database
        self.frame_period_s = 1.0 / telemetry_rate_hz
        self.flush_interval_s = flush_interval_s
        self.tail_s = tail_s
        self._lock = threading.Lock()
        self._run_id: int | None = None
        self._session_id: int | None = None
        self._confirmed = False
        self._pending: list[np.ndarray] = []
        self._sequence = 0
        self._last_flush = time.monotonic()
        self._tail_deadline: float | None = None
        self._buffering = False  # between begin_run and the end of the run
        self._subscribers: set[asyncio.Queue[str]] = set()

    # --- run lifecycle (called by run control, from request threads) -----------------------------

    def begin_run(self, session_id: int) -> None:
        """Start buffering for a run about to be started; nothing is written until `confirm_run`."""
        self.finish_run()
        with self._lock:
            self._run_id, self._session_id = None, session_id
            self._confirmed, self._pending, self._sequence, self._tail_deadline = False, [], 0, None
            self._buffering = True

    def confirm_run(self, run_id: int) -> None:
        """The run is recorded: what was buffered since `begin_run` belongs to it."""
        with self._lock:
            self._run_id, self._confirmed = run_id, True

    def abandon_run(self) -> None:
        with self._lock:
            self._run_id = self._session_id = None
            self._pending, self._buffering = [], False

    def end_run_after_tail(self) -> None:
        with self._lock:
            if self._buffering and self._tail_deadline is None:
                self._tail_deadline = time.monotonic() + self.tail_s

    def finish_run(self) -> None:
        """Write what is buffered and stop recording the current run."""
        self.flush()
        with self._lock:
            self._run_id = self._session_id = None
            self._tail_deadline, self._buffering = None, False

    @property
    def active_run_id(self) -> int | None:
        return self._run_id

    # --- the pump (a thread, once per frame) ---------------------------------------------------

    def pump(self) -> str:
        """Drain the worker once, record, and return the frame (JSON text) for the WebSocket clients."""
        telemetry = self.worker.drain_telemetry()
        events = self.worker.drain_events()
        state = self.worker.latest_state()
        with self._lock:
            run_id, session_id = self._run_id, self._session_id
            if self._buffering and telemetry is not None and len(telemetry):
                self._pending.append(np.array(telemetry, copy=True))
            flush_due = self._confirmed and time.monotonic() - self._last_flush >= self.flush_interval_s
            tail_over = self._tail_deadline is not None and time.monotonic() >= self._tail_deadline
        if events:
            self._store_events(run_id, events)
        if tail_over:
            self.finish_run()
        elif flush_due:
            self.flush()
        latest_sample = None
        if telemetry is not None and len(telemetry):
            last = telemetry[-1]
            latest_sample = {name: last[name] for name in telemetry.dtype.names or ()}
        frame = {
            "type": "telemetry",
            "utc": dt.datetime.now(dt.UTC).isoformat(),
            "run_id": run_id,
            "session_id": session_id,
            "state": state,
            "sample": latest_sample,
            "events": events,
        }
        return json.dumps(to_jsonable(frame))

    def flush(self) -> None:
        with self._lock:
            run_id, confirmed, chunks = self._run_id, self._confirmed, self._pending
            if run_id is None or not confirmed or not chunks:
                self._last_flush = time.monotonic()
                return
            self._pending = []
            sequence = self._sequence
            self._sequence += 1
            self._last_flush = time.monotonic()
        records = np.concatenate(chunks)
        first_tick = int(records["tick"][0]) if "tick" in (records.dtype.names or ()) else 0
        with self.database.session() as session, write_transaction(session):
            session.add(
                TelemetryChunk(
                    run_id=run_id,
                    sequence=sequence,
                    first_tick=first_tick,
                    sample_count=len(records),
                    data=encode_chunk(records),
                )
            )
            run = session.get(SessionRun, run_id)
            if run is not None:
                run.sample_count += len(records)

    def _store_events(self, run_id: int | None, events: list[dict[str, Any]]) -> None:
        terminal_outcome = None
        with self.database.session() as session, write_transaction(session):
            for event in events:
                kind = str(event.get("kind", "unknown"))[:32]
                session.add(
                    SessionEvent(
                        run_id=run_id,
                        kind=kind,
                        tick=int(event["tick"]) if event.get("tick") is not None else None,
                        tick_time_s=float(event["tick_time_s"]) if event.get("tick_time_s") is not None else None,
                        utc=event_utc(event.get("utc")),
                        detector=str(event["detector"])[:64] if event.get("detector") else None,
                        details=to_jsonable(event.get("details") or {}),
                    )
                )
                terminal_outcome = terminal_outcome or terminal_outcome_of(kind, event.get("details") or {})
            if run_id is not None and terminal_outcome is not None:
                self._end_run(session, run_id, terminal_outcome)
        if terminal_outcome is not None:
            self.end_run_after_tail()

    @staticmethod
    def _end_run(session: Any, run_id: int, outcome: str) -> None:
        run = session.get(SessionRun, run_id)
        if run is None or run.state not in ACTIVE_STATES:
            return
        run.state, run.outcome, run.ended_at = "ended", outcome, dt.datetime.now(dt.UTC)
        if outcome == "completed":
            booking = session.scalar(select(ScheduledSession).where(ScheduledSession.id == run.scheduled_session_id))
            if booking is not None:
                booking.status = "completed"

    # --- fan-out (event loop) ------------------------------------------------------------------

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
                self.broadcast(await asyncio.to_thread(self.pump))
            except Exception:
                logger.exception("session recorder: one frame failed")
            # Absolute frame times, so that sleep overshoot does not add up and lower the frame rate;
            # after falling more than a frame behind, restart the schedule rather than burst.
            next_frame += self.frame_period_s
            if next_frame < loop.time() - self.frame_period_s:
                next_frame = loop.time()
            await asyncio.sleep(max(0.0, next_frame - loop.time()))
