"""One trial of issue 20's defect 2 against a real console: a start whose prescription is still being planned
and checked, an emergency stop during that load, then a reset. The start must be cancelled (refused), no
run recorded, and the robot must not move afterwards. Used by tests/server/test_start_cancel.py and
`ssp-rehab bench faults` (10 trials)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from benchmarks.fault_harness import EVENT_TIMEOUT_S, SHORT_SINE, Console, in_background, wait_for

LONG_LOAD_S = 900.0  # one sine segment this long: its offline check takes many seconds
MOTION_STATES = ("running", "paused", "stopping")
WATCH_AFTER_ANSWER_S = 2.0  # how long the robot is watched for motion after the start answered


@dataclass
class StartCancelOutcome:
    start_status: int | None
    detail: str
    cancelled: bool  # the start was refused because of the emergency stop
    moved: bool  # the robot was seen moving, or a run recorded, after the emergency stop
    runs_recorded: int
    estop_status: int
    estop_round_trip_ms: float
    estop_confirmed_after_ms: float | None  # the handler's store of the flag → the worker shows it latched
    reset_status: int
    estop_to_start_answer_s: float


def planning_started(console: Console, session_id: int) -> bool:
    """The robot daemon has begun planning this session's prescription (its log says so)."""
    log = console.data_dir / "robots" / f"{console.robot}.log"
    return log.exists() and f"session {session_id}: planning" in log.read_text(errors="replace")


def cancel_loading_start(console: Console, *, segment_s: float = LONG_LOAD_S) -> StartCancelOutcome:
    """Start, emergency stop while the daemon plans, reset; then what the start answered and whether anything
    moved. Leaves the robot standing still and reset."""
    session_id = console.book(segments=[{"cue": SHORT_SINE, "duration_s": segment_s}])
    starter, answers = in_background(lambda: console.post(f"/sessions/{session_id}/start", timeout=1800.0))
    wait_for(lambda: planning_started(console, session_id), EVENT_TIMEOUT_S, f"session {session_id} to be planned")
    estop_at = time.monotonic()
    estop = console.post("/estop")
    estop_ms = (time.monotonic() - estop_at) * 1e3
    reset = console.post("/robot/reset")
    starter.join(1800.0)
    answered_s = time.monotonic() - estop_at
    answer: Any = answers[0] if answers else None
    status = answer.status_code if answer is not None and not isinstance(answer, Exception) else None
    detail = answer.text if status is not None else repr(answer)
    moved = False
    watch_until = time.monotonic() + WATCH_AFTER_ANSWER_S
    while time.monotonic() < watch_until and not moved:
        moved = console.get("/robot/state").json().get("state") in MOTION_STATES
        time.sleep(0.05)
    runs = console.runs(session_id)
    for run in runs:  # put the robot back at rest for the next trial
        if run["state"] != "ended":
            console.post(f"/sessions/{session_id}/stop")
    if runs:
        wait_for(
            lambda: console.get("/robot/state").json().get("state") not in MOTION_STATES,
            EVENT_TIMEOUT_S,
            "the robot to stand still",
        )
        console.post("/robot/reset")
    return StartCancelOutcome(
        start_status=status,
        detail=detail[:300],
        cancelled=status == 409 and "start cancelled by the emergency stop" in detail,
        moved=moved or bool(runs),
        runs_recorded=len(runs),
        estop_status=estop.status_code,
        estop_round_trip_ms=round(estop_ms, 2),
        estop_confirmed_after_ms=estop.json().get("confirmed_after_ms") if estop.status_code == 200 else None,
        reset_status=reset.status_code,
        estop_to_start_answer_s=round(answered_s, 3),
    )
