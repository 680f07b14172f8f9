"""Session-run and event answers."""

from __future__ import annotations

import datetime as dt
from typing import Any, Literal

from server.api_types import ResponseModel


class SessionRunOut(ResponseModel):
    id: int
    scheduled_session_id: int
    prescription_version_id: int
    robot: str
    state: str
    outcome: str | None
    started_at: dt.datetime
    ended_at: dt.datetime | None
    started_by_id: int | None
    stopped_by_id: int | None
    sample_count: int


class StartCancelledOut(ResponseModel):
    """The answer to a stop that came while the session's start was still loading: the start is cancelled."""

    scheduled_session_id: int
    status: Literal["start cancelled"] = "start cancelled"
    detail: str


class SessionEventOut(ResponseModel):
    id: int
    run_id: int | None
    kind: str
    tick: int | None
    tick_time_s: float | None
    utc: dt.datetime
    detector: str | None
    details: dict[str, Any]
    user_id: int | None


class EmergencyStopResult(ResponseModel):
    status: str
    utc: dt.datetime
    confirmed_after_ms: float | None = None  # from storing the latched flag to the worker showing it latched
