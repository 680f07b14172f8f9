"""Run records: the robot daemon (server.robotd) decides every change of a run and records it here, with
the run id it chose. A run starts with `record_start`, changes with `record_command` and ends only
through `end_run`, whatever ended it (stop, emergency stop, completion, fault, fall, interruption).
Web processes read runs and events; they never write them.
"""

from __future__ import annotations

import datetime as dt
import logging
from typing import Any, Literal

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.audit import service as audit
from server.db import writes
from server.errors import ConflictError, InvalidFieldError, NotFoundError
from server.patients.models import Patient
from server.prescriptions.models import PrescriptionVersion
from server.robotd.models import ACTIVE_STATES, RunOutcome, RunState, SessionEvent, SessionRun
from server.scheduling.models import ScheduledSession
from server.scheduling.service import get_booking

logger = logging.getLogger(__name__)

RunCommand = Literal["pause", "resume", "stop"]
# Which run state each command needs, and the state it leaves.
TRANSITIONS: dict[str, tuple[tuple[RunState, ...], RunState]] = {
    "pause": ((RunState.RUNNING,), RunState.PAUSED),
    "resume": ((RunState.PAUSED,), RunState.RUNNING),
    "stop": (ACTIVE_STATES, RunState.ENDED),
}
Clock = tuple[int | None, float | None]  # the worker's tick and tick time, to stamp console events
NO_CLOCK: Clock = (None, None)


def get_run(*, session: Session, run_id: int) -> SessionRun:
    run = session.get(SessionRun, run_id)
    if run is None:
        raise NotFoundError("session run", run_id)
    return run


def active_run_on_robot(*, session: Session, robot: str) -> SessionRun | None:
    return session.scalar(
        select(SessionRun).where(SessionRun.robot == robot, SessionRun.state.in_(ACTIVE_STATES)).limit(1)
    )


def runs_of_booking(*, session: Session, session_id: int) -> list[SessionRun]:
    get_booking(session=session, session_id=session_id)
    return list(
        session.scalars(select(SessionRun).where(SessionRun.scheduled_session_id == session_id).order_by(SessionRun.id))
    )


def events_of_run(*, session: Session, run_id: int) -> list[SessionEvent]:
    get_run(session=session, run_id=run_id)
    return list(session.scalars(select(SessionEvent).where(SessionEvent.run_id == run_id).order_by(SessionEvent.id)))


def patient_for_worker(patient: Patient) -> dict[str, Any]:
    """What the worker's dynamics payload, simulated patient and fall thresholds need: anthropometrics only."""
    return {"body_mass_kg": patient.body_mass_kg, "height_m": patient.height_m}


def add_event(
    *,
    session: Session,
    run_id: int | None,
    kind: str,
    user_id: int | None,
    clock: Clock = NO_CLOCK,
    details: dict[str, Any] | None = None,
    detector: str = "console",
    utc: dt.datetime | None = None,
) -> SessionEvent:
    tick, tick_time_s = clock
    event = SessionEvent(
        run_id=run_id,
        kind=kind,
        tick=tick,
        tick_time_s=tick_time_s,
        detector=detector,
        details=details or {},
        user_id=user_id,
        utc=utc or dt.datetime.now(dt.UTC),
    )
    session.add(event)
    return event


def refused(error: Exception) -> Exception:
    """A worker refusal as a client error: a prescription over a limit (PrescriptionRejected) or an invalid
    prescription (PrescriptionError: field, value, limit) is bad input; anything else is a conflict."""
    segment, limit = getattr(error, "segment", None), getattr(error, "limit", None)
    if segment is not None and limit is not None:
        time_s = getattr(error, "time_s", None)
        where = f" at t = {time_s:.3f} s" if isinstance(time_s, int | float) else ""
        details = {"segment": segment, "time_s": time_s, **getattr(error, "details", {})}
        return InvalidFieldError(
            f"segments[{segment}]", getattr(error, "value", None), f"{limit}{where}: {error}", details=details
        )
    field = getattr(error, "field", None)
    if field is not None and limit is not None:
        return InvalidFieldError(str(field), getattr(error, "value", None), str(limit))
    return ConflictError(f"the robot refused the command: {error}")


def plan_inputs(*, session: Session, session_id: int) -> tuple[ScheduledSession, PrescriptionVersion, Patient]:
    """The booking, its prescription version and patient: what its plan is made from."""
    booking = get_booking(session=session, session_id=session_id)
    version = session.get(PrescriptionVersion, booking.prescription_version_id)
    patient = session.get(Patient, booking.patient_id)
    assert version is not None and patient is not None  # foreign keys guarantee both
    return booking, version, patient


def startable(
    *, session: Session, session_id: int, robot: str
) -> tuple[ScheduledSession, PrescriptionVersion, Patient]:
    """The booking, its prescription version and patient, if `robot` may start it now; else the refusal."""
    booking = get_booking(session=session, session_id=session_id)
    if booking.status == "cancelled":
        raise ConflictError(f"session {session_id} is cancelled", field="status")
    if booking.robot != robot:
        raise ConflictError(
            f"session {session_id} is booked on robot {booking.robot!r}; this console controls robot {robot!r}",
            field="robot",
        )
    busy = active_run_on_robot(session=session, robot=robot)
    if busy is not None:
        raise ConflictError(f"robot {robot!r} is busy with run {busy.id} (session {busy.scheduled_session_id})")
    version = session.get(PrescriptionVersion, booking.prescription_version_id)
    patient = session.get(Patient, booking.patient_id)
    assert version is not None and patient is not None  # foreign keys guarantee both
    return booking, version, patient


@writes
def record_start(
    *, session: Session, booking_id: int, robot: str, patient_id: int, version_id: int, clock: Clock, actor_id: int
) -> SessionRun:
    busy = active_run_on_robot(session=session, robot=robot)  # inside the write lock
    if busy is not None:
        raise ConflictError(f"robot {robot!r} is busy with run {busy.id} (session {busy.scheduled_session_id})")
    run = SessionRun(
        scheduled_session_id=booking_id,
        prescription_version_id=version_id,
        robot=robot,
        state=RunState.RUNNING.value,
        started_by_id=actor_id,
    )
    session.add(run)
    session.flush()
    add_event(
        session=session,
        run_id=run.id,
        kind="start",
        user_id=actor_id,
        clock=clock,
        details={"prescription_version_id": version_id},
    )
    _audit_motion(session, actor_id, run.id, "start", patient_id=patient_id)
    return run


def check_command(run_state: RunState | None, session_id: int, command: RunCommand) -> RunState:
    """The state `command` leaves, or the 409 saying which state it needs."""
    needed, next_state = TRANSITIONS[command]
    if run_state is None or run_state not in needed:
        state = run_state.value if run_state else "no active run"
        raise ConflictError(
            f"cannot {command} session {session_id}: {state} (needs {' or '.join(s.value for s in needed)})"
        )
    return next_state


@writes
def record_command(
    *,
    session: Session,
    run_id: int,
    command: RunCommand,
    clock: Clock,
    actor_id: int,
    at: dt.datetime | None = None,
    credential: str | None = None,
) -> SessionRun:
    """A pause or resume (a stop is recorded by `end_run`), at the time the daemon decided it. A run that
    ended meanwhile (the database caught up late) keeps its end; the command is still recorded."""
    run = get_run(session=session, run_id=run_id)
    if run.state != RunState.ENDED:
        run.state = TRANSITIONS[command][1].value
    details = {"credential": credential} if credential else None
    add_event(session=session, run_id=run.id, kind=command, user_id=actor_id, clock=clock, details=details, utc=at)
    _audit_motion(session, actor_id, run.id, command, credential=credential)
    return run


def _audit_motion(
    session: Session,
    actor_id: int | None,
    run_id: int,
    command: str,
    *,
    credential: str | None = None,
    patient_id: int | None = None,
) -> None:
    details: dict[str, object] = {"command": command}
    if patient_id is not None:
        details["patient_id"] = patient_id
    if credential:
        details["credential"] = credential
    audit.record(
        session=session,
        user_id=actor_id,
        action="motion",
        resource_type="session_run",
        resource_id=run_id,
        details=details,
    )


@writes
def end_run(
    *,
    session: Session,
    run_id: int,
    outcome: RunOutcome,
    at: dt.datetime,
    reason: str,
    clock: Clock = NO_CLOCK,
    stopped_by_id: int | None = None,
    credential: str | None = None,
) -> SessionRun | None:
    """The one way a run ends: its state, outcome, true end time, who stopped it, a `run_ended` event, and
    the booking completed when the prescription was. A run that already ended is left as it is (the first
    end wins), except that a later-known operator is filled in. None when the run does not exist."""
    run = session.get(SessionRun, run_id)
    if run is None:
        return None
    if run.state == RunState.ENDED:
        if stopped_by_id is not None and run.stopped_by_id is None:
            run.stopped_by_id = stopped_by_id
        return run
    run.state, run.outcome, run.ended_at = RunState.ENDED.value, outcome.value, at
    run.stopped_by_id = stopped_by_id
    if outcome == RunOutcome.STOPPED:
        details = {"credential": credential} if credential else None
        add_event(
            session=session, run_id=run.id, kind="stop", user_id=stopped_by_id, clock=clock, utc=at, details=details
        )
        _audit_motion(session, stopped_by_id, run.id, "stop", credential=credential)
    add_event(
        session=session,
        run_id=run.id,
        kind="run_ended",
        user_id=stopped_by_id,
        clock=clock,
        details={"outcome": outcome.value, "reason": reason},
        detector="robot daemon",
        utc=at,
    )
    if outcome == RunOutcome.COMPLETED:
        booking = session.get(ScheduledSession, run.scheduled_session_id)
        if booking is not None:
            booking.status = "completed"
    return run


@writes
def record_emergency_stop(
    *, session: Session, user_id: int | None, authenticated: bool, credential: str, run_ids: list[int], clock: Clock
) -> None:
    """Who asked for an emergency stop, truthfully: a user only when the request proved one."""
    details = {"authenticated": authenticated, "credential": credential}
    for run_id in run_ids or [None]:  # type: ignore[list-item]
        add_event(session=session, run_id=run_id, kind="emergency_stop", user_id=user_id, clock=clock, details=details)
    audit.record(
        session=session,
        user_id=user_id,
        action="motion",
        resource_type="robot",
        details={"command": "emergency_stop", "run_ids": run_ids, **details},
    )


@writes
def record_robot_command(*, session: Session, user_id: int, command: str, clock: Clock) -> None:
    add_event(session=session, run_id=None, kind=command, user_id=user_id, clock=clock)
    audit.record(session=session, user_id=user_id, action="motion", resource_type="robot", details={"command": command})
