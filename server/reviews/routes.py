"""`/runs/{id}/review`, `/runs/{id}/acknowledge`, `/runs/{id}/notes`, `/reviews/pending`."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query, Request

from server.api_types import NO_NUL_PATTERN, IdPath
from server.auth.access import ObjectAccess, require_object
from server.auth.dependencies import CurrentUser, current_user
from server.db import SessionDep
from server.errors import NotFoundError
from server.reviews import service
from server.reviews.schemas import AcknowledgementIn, AcknowledgementOut, RunNotesIn, RunNotesOut, RunReviewOut

router = APIRouter(tags=["reviews"], dependencies=[Depends(current_user), ObjectAccess])
RobotName = Annotated[
    str | None,
    Query(min_length=1, max_length=64, pattern=NO_NUL_PATTERN, description="Robot name (default: this console's)."),
]


@router.get("/runs/{run_id}/review", response_model=RunReviewOut)
def run_review(run_id: IdPath, session: SessionDep) -> RunReviewOut:
    """Whether the run's stop (emergency stop, interruption, fault, fall, limit stop) still needs an
    acknowledgement, who gave it, and the run's notes."""
    return service.review(session=session, run_id=run_id)


@router.post(
    "/runs/{run_id}/acknowledge",
    response_model=AcknowledgementOut,
    responses={409: {"description": "Nothing to acknowledge"}},
)
def acknowledge_run(
    run_id: IdPath, data: AcknowledgementIn, session: SessionDep, user: CurrentUser
) -> AcknowledgementOut:
    """Records (as an `acknowledged` event of the run) that the therapist attended to a stop that moved the
    patient (emergency stop, interruption, fault, fall, limit stop): the robot starts again only after it."""
    return service.acknowledge(session=session, run_id=run_id, user_id=user.id, note=data.note)


@router.put("/runs/{run_id}/notes", response_model=RunNotesOut)
def save_run_notes(run_id: IdPath, data: RunNotesIn, session: SessionDep, user: CurrentUser) -> RunNotesOut:
    """The therapist's SOAP notes of the run (replaces the previous text; each save is audited)."""
    return service.save_notes(session=session, run_id=run_id, data=data, user_id=user.id)


@router.get("/reviews/pending", response_model=RunReviewOut | None)
def pending_acknowledgement(
    request: Request, session: SessionDep, user: CurrentUser, robot: RobotName = None
) -> RunReviewOut | None:
    """The robot's last run if it ended in a stop that moved the patient, not yet acknowledged; else null.
    Every user of the robot sees that it is pending; its notes only the run's care team."""
    pending = service.pending_on_robot(session=session, robot=robot or request.app.state.settings.robot)
    if pending is None:
        return None
    try:
        require_object(session, user, "run_id", pending.run_id)
    except NotFoundError:
        return pending.model_copy(update={"notes": RunNotesOut(run_id=pending.run_id, author_id=None, updated_at=None)})
    return pending
