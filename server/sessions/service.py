"""Run control: start, pause, resume and stop a scheduled session on the robot, recording the run, its
events and an audit entry for every motion command.

The worker is commanded inside the transaction that records the command, so a refused command leaves
nothing written, and a run that cannot be recorded is stopped again.
"""

from __future__ import annotations

import datetime as dt
import logging
from typing import TYPE_CHECKING, Any, Literal

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.audit import service as audit
from server.db import writes
from server.errors import ConflictError, InvalidFieldError, NotFoundError
from server.patients.models import Patient
from server.prescriptions.models import PrescriptionVersion
from server.scheduling.service import get_booking
from server.sessions.models import SessionEvent, SessionRun
from server.sessions.worker import WorkerControl

if TYPE_CHECKING:
    from server.sessions.recorder import SessionRecorder

logger = logging.getLogger(__name__)

ACTIVE_STATES = ("running", "paused")
RunCommand = Literal["pause", "resume", "stop"]
# Which run state each command needs, and the state it leaves.
TRANSITIONS: dict[str, tuple[tuple[str, ...], str]] = {
    "pause": (("running",), "paused"),
    "resume": (("paused",), "running"),
    "stop": (ACTIVE_STATES, "ended"),
}


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


def worker_clock(worker: WorkerControl) -> tuple[int | None, float | None]:
    """The worker's current tick and tick time, for stamping console commands; (None, None) if unknown."""
    try:
        state = worker.latest_state()
    except Exception:
        return None, None
    tick, time_s = state.get("tick"), state.get("time_s")
    return (int(tick) if tick is not None else None), (float(time_s) if time_s is not None else None)


def add_event(
    *,
    session: Session,
    run_id: int | None,
    kind: str,
    user_id: int | None,
    worker: WorkerControl | None,
    details: dict[str, Any] | None = None,
    detector: str = "console",
) -> SessionEvent:
    tick, tick_time_s = worker_clock(worker) if worker is not None else (None, None)
    event = SessionEvent(
        run_id=run_id,
        kind=kind,
        tick=tick,
        tick_time_s=tick_time_s,
        detector=detector,
        details=details or {},
        user_id=user_id,
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
        return InvalidFieldError(f"segments[{segment}]", getattr(error, "value", None), f"{limit}{where}: {error}")
    field = getattr(error, "field", None)
    if field is not None and limit is not None:
        return InvalidFieldError(str(field), getattr(error, "value", None), str(limit))
    return ConflictError(f"the robot refused the command: {error}")


def start_run(
    *, session: Session, session_id: int, worker: WorkerControl, actor_id: int, recorder: SessionRecorder | None
) -> SessionRun:
    """Check, command the worker, then record: the SQLite write lock is not held while the worker loads
    (and checks) the prescription. If the run cannot be recorded, the robot is stopped again."""
    booking = get_booking(session=session, session_id=session_id)
    if booking.status == "cancelled":
        raise ConflictError(f"session {session_id} is cancelled", field="status")
    _refuse_if_busy(session, booking.robot)
    version = session.get(PrescriptionVersion, booking.prescription_version_id)
    patient = session.get(Patient, booking.patient_id)
    assert version is not None and patient is not None  # foreign keys guarantee both
    session.commit()  # ends the read; nothing was written
    if recorder is not None:
        recorder.begin_run(booking.id)
    try:
        worker.load_prescription(version.content, patient_for_worker(patient))
        worker.start_motion()
    except Exception as error:
        logger.warning("worker refused to start session %d: %s", session_id, type(error).__name__)
        if recorder is not None:
            recorder.abandon_run()
        raise refused(error) from error
    try:
        run = _record_start(
            session=session,
            booking_id=booking.id,
            robot=booking.robot,
            patient_id=booking.patient_id,
            version_id=version.id,
            worker=worker,
            actor_id=actor_id,
        )
    except Exception:
        # Motion without a record of it is not allowed: stop the robot, then report the failure.
        worker.stop()
        if recorder is not None:
            recorder.abandon_run()
        raise
    if recorder is not None:
        recorder.confirm_run(run.id)
    return run


def _refuse_if_busy(session: Session, robot: str) -> None:
    busy = active_run_on_robot(session=session, robot=robot)
    if busy is not None:
        raise ConflictError(f"robot {robot!r} is busy with run {busy.id} (session {busy.scheduled_session_id})")


@writes
def _record_start(
    *,
    session: Session,
    booking_id: int,
    robot: str,
    patient_id: int,
    version_id: int,
    worker: WorkerControl,
    actor_id: int,
) -> SessionRun:
    _refuse_if_busy(session, robot)  # again, inside the write lock: another start may have won the race
    run = SessionRun(
        scheduled_session_id=booking_id,
        prescription_version_id=version_id,
        robot=robot,
        state="running",
        started_by_id=actor_id,
    )
    session.add(run)
    session.flush()
    add_event(
        session=session,
        run_id=run.id,
        kind="start",
        user_id=actor_id,
        worker=worker,
        details={"prescription_version_id": version_id},
    )
    audit.record(
        session=session,
        user_id=actor_id,
        action="motion",
        resource_type="session_run",
        resource_id=run.id,
        details={"command": "start", "patient_id": patient_id},
    )
    return run


@writes
def control_run(
    *, session: Session, session_id: int, command: RunCommand, worker: WorkerControl, actor_id: int
) -> SessionRun:
    get_booking(session=session, session_id=session_id)
    run = session.scalar(
        select(SessionRun)
        .where(SessionRun.scheduled_session_id == session_id, SessionRun.state.in_(ACTIVE_STATES))
        .limit(1)
    )
    needed, next_state = TRANSITIONS[command]
    if run is None or run.state not in needed:
        state = run.state if run else "no active run"
        raise ConflictError(f"cannot {command} session {session_id}: {state} (needs {' or '.join(needed)})")
    try:
        getattr(worker, command)()
    except Exception as error:
        session.rollback()
        raise refused(error) from error
    run.state = next_state
    if command == "stop":
        run.outcome, run.ended_at, run.stopped_by_id = "stopped", dt.datetime.now(dt.UTC), actor_id
    add_event(session=session, run_id=run.id, kind=command, user_id=actor_id, worker=worker)
    audit.record(
        session=session,
        user_id=actor_id,
        action="motion",
        resource_type="session_run",
        resource_id=run.id,
        details={"command": command},
    )
    return run


@writes
def record_emergency_stop(*, session: Session, user_id: int, worker: WorkerControl | None) -> None:
    """After the worker has the emergency stop: end every active run and record who pressed it."""
    runs = list(session.scalars(select(SessionRun).where(SessionRun.state.in_(ACTIVE_STATES))))
    now = dt.datetime.now(dt.UTC)
    for run in runs:
        run.state, run.outcome, run.ended_at, run.stopped_by_id = "ended", "emergency_stop", now, user_id
        add_event(session=session, run_id=run.id, kind="emergency_stop", user_id=user_id, worker=worker)
    if not runs:
        add_event(session=session, run_id=None, kind="emergency_stop", user_id=user_id, worker=worker)
    audit.record(
        session=session,
        user_id=user_id,
        action="motion",
        resource_type="robot",
        details={"command": "emergency_stop", "run_ids": [r.id for r in runs]},
    )


@writes
def record_robot_command(*, session: Session, user_id: int, command: str, worker: WorkerControl) -> None:
    add_event(session=session, run_id=None, kind=command, user_id=user_id, worker=worker)
    audit.record(session=session, user_id=user_id, action="motion", resource_type="robot", details={"command": command})
