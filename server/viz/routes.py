"""`/viz`: where the live 3D view listens (the session page embeds it), and its replay of a finished run."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Depends, Request
from pydantic import ConfigDict, Field

from server.api_types import MAX_ID, RequestModel
from server.audit import service as audit
from server.auth.dependencies import CurrentUser, current_user
from server.db import SessionDep
from server.errors import ConflictError, WorkerUnavailableError
from server.sessions.logs import telemetry_columns
from server.sessions.service import get_run
from server.viz.view import LiveView, ReplayError

router = APIRouter(prefix="/viz", tags=["3d view"], dependencies=[Depends(current_user)])

NO_VIEW = "the 3D view is not running (turned off with SSP_REHAB_VIZ_ENABLED=false, or its port was taken)"


class ReplayRequest(RequestModel):
    run_id: Annotated[int, Field(ge=1, le=MAX_ID)]

    model_config = ConfigDict(json_schema_extra={"examples": [{"run_id": 1}]})


def _view(request: Request) -> LiveView:
    view: LiveView | None = getattr(request.app.state, "viz", None)
    if view is None:
        raise WorkerUnavailableError(NO_VIEW)
    return view


@router.get("")
def view_status(request: Request) -> dict[str, Any]:
    """The view's port (the page builds `http://<this host>:<port>/`), mode (live or replay) and frames shown."""
    view: LiveView | None = getattr(request.app.state, "viz", None)
    if view is None:
        return {"available": False, "detail": NO_VIEW}
    return view.status()


@router.post("/replay", responses={503: {"description": "No 3D view"}, 409: {"description": "No telemetry"}})
def replay_run(data: ReplayRequest, request: Request, session: SessionDep, user: CurrentUser) -> dict[str, Any]:
    """Play a recorded run in the 3D view at its recorded speed; `POST /viz/live` returns to the robot."""
    view = _view(request)
    run = get_run(session=session, run_id=data.run_id)
    columns = telemetry_columns(session=session, run_id=run.id)
    try:
        view.replay(run.id, columns)
    except ReplayError as error:
        raise ConflictError(f"session run {run.id} cannot be replayed: {error}", field=error.field) from error
    audit.record(session=session, user_id=user.id, action="replay", resource_type="session_run", resource_id=run.id)
    session.commit()
    return view.status()


@router.post("/live", responses={503: {"description": "No 3D view"}})
def go_live(request: Request) -> dict[str, Any]:
    """Leave replay: the view follows the robot again."""
    view = _view(request)
    view.go_live()
    return view.status()
