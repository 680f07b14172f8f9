"""Run reviews. A run ended by a stop that moved the patient (an emergency stop, the watchdog or another
interruption, a fault, a fall, a limit stop) needs an acknowledgement before the robot it ran on starts
again (issue 20, build 9); the therapist's own stop and a completed run do not. The acknowledgement is an
event of that run (who, when, what was checked), so it stands in the run's record, its exports and its
report."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.orm import Session

from server.audit import service as audit
from server.db import writes
from server.errors import ConflictError
from server.reviews.models import RunNote
from server.reviews.schemas import AcknowledgementOut, RunNotesIn, RunNotesOut, RunReviewOut
from server.robotd.models import RunOutcome, RunState, SessionEvent, SessionRun
from server.robotd.runs import add_event, get_run
from server.scheduling.service import get_booking

# Each outcome that needs an acknowledgement, in the words of the refusal.
STOPS_NEEDING_ACKNOWLEDGEMENT = {
    RunOutcome.EMERGENCY_STOP: "emergency stop",
    RunOutcome.INTERRUPTED: "interruption (watchdog or lost connection)",
    RunOutcome.FAULT: "fault",
    RunOutcome.FALL: "fall",
    RunOutcome.LIMIT_HIT: "limit stop",
}
OUTCOMES_NEEDING_ACKNOWLEDGEMENT = frozenset(STOPS_NEEDING_ACKNOWLEDGEMENT)
ACKNOWLEDGED = "acknowledged"


def _acknowledgement(session: Session, run: SessionRun) -> SessionEvent | None:
    return session.scalars(
        select(SessionEvent)
        .where(SessionEvent.run_id == run.id, SessionEvent.kind == ACKNOWLEDGED)
        .order_by(SessionEvent.id.desc())
    ).first()


def _acknowledgement_out(event: SessionEvent) -> AcknowledgementOut:
    return AcknowledgementOut(
        event_id=event.id,
        run_id=int(event.run_id or 0),
        outcome=str(event.details.get("outcome", "")),
        user_id=event.user_id,
        utc=event.utc,
        note=str(event.details.get("note", "")),
    )


def needs_acknowledgement(session: Session, run: SessionRun) -> bool:
    return (
        run.state == RunState.ENDED
        and run.outcome in OUTCOMES_NEEDING_ACKNOWLEDGEMENT
        and _acknowledgement(session, run) is None
    )


def notes_of(session: Session, run_id: int) -> RunNotesOut:
    note = session.get(RunNote, run_id)
    if note is None:
        return RunNotesOut(run_id=run_id, author_id=None, updated_at=None)
    return RunNotesOut(
        run_id=run_id,
        subjective=note.subjective,
        objective=note.objective,
        assessment=note.assessment,
        plan=note.plan,
        author_id=note.author_id,
        updated_at=note.updated_at,
    )


def review_of(session: Session, run: SessionRun) -> RunReviewOut:
    event = _acknowledgement(session, run)
    return RunReviewOut(
        run_id=run.id,
        robot=run.robot,
        outcome=run.outcome,
        needs_acknowledgement=needs_acknowledgement(session, run),
        acknowledgement=_acknowledgement_out(event) if event is not None else None,
        notes=notes_of(session, run.id),
    )


def review(*, session: Session, run_id: int) -> RunReviewOut:
    return review_of(session, get_run(session=session, run_id=run_id))


def pending_on_robot(*, session: Session, robot: str) -> RunReviewOut | None:
    """The robot's last ended run, if it needs an acknowledgement: only the latest run counts, because the
    robot has run normally since any earlier one."""
    last = session.scalars(
        select(SessionRun)
        .where(SessionRun.robot == robot, SessionRun.state == RunState.ENDED)
        .order_by(SessionRun.ended_at.desc(), SessionRun.id.desc())
    ).first()
    if last is None or not needs_acknowledgement(session, last):
        return None
    return review_of(session, last)


def stop_words(outcome: str | None) -> str:
    """The stop in the clinician's words ("emergency stop", "limit stop", …)."""
    known = {str(stop): words for stop, words in STOPS_NEEDING_ACKNOWLEDGEMENT.items()}
    return known.get(outcome or "", (outcome or "stop").replace("_", " "))


def refuse_start_while_unacknowledged(*, session: Session, session_id: int) -> None:
    """Refuses to start motion on a robot whose last run ended in a stop that moved the patient and that
    nobody acknowledged; checked before the worker is commanded (nothing moves, nothing is written)."""
    booking = get_booking(session=session, session_id=session_id)
    pending = pending_on_robot(session=session, robot=booking.robot)
    if pending is not None:
        what = stop_words(pending.outcome)
        article = "an" if what[0] in "aeiou" else "a"
        raise ConflictError(
            f"run {pending.run_id} on {booking.robot} ended with {article} {what} that is not acknowledged: "
            f"acknowledge it (POST /api/v1/runs/{pending.run_id}/acknowledge) before the robot starts again",
            field="acknowledgement",
        )


@writes
def acknowledge(*, session: Session, run_id: int, user_id: int, note: str) -> AcknowledgementOut:
    run = get_run(session=session, run_id=run_id)
    if run.state != RunState.ENDED or run.outcome not in OUTCOMES_NEEDING_ACKNOWLEDGEMENT:
        raise ConflictError(
            f"run {run_id} ended as {run.outcome or run.state}: nothing to acknowledge (only a stop that moved the "
            "patient is: an emergency stop, an interruption, a fault, a fall or a limit stop)"
        )
    if _acknowledgement(session, run) is not None:
        raise ConflictError(f"the {stop_words(run.outcome)} of run {run_id} is already acknowledged")
    event = add_event(
        session=session,
        run_id=run.id,
        kind=ACKNOWLEDGED,
        user_id=user_id,
        details={"outcome": run.outcome, "note": note},
    )
    session.flush()
    audit.record(
        session=session, user_id=user_id, action="acknowledge", resource_type="session_run", resource_id=run.id,
        details={"outcome": run.outcome},
    )  # fmt: skip
    return _acknowledgement_out(event)


@writes
def save_notes(*, session: Session, run_id: int, data: RunNotesIn, user_id: int) -> RunNotesOut:
    run = get_run(session=session, run_id=run_id)
    note = session.get(RunNote, run.id)
    if note is None:
        note = RunNote(run_id=run.id)
        session.add(note)
    for name, value in data.model_dump().items():
        setattr(note, name, value)
    note.author_id = user_id
    session.flush()
    audit.record(session=session, user_id=user_id, action="update", resource_type="run_notes", resource_id=run.id)
    return notes_of(session, run.id)
