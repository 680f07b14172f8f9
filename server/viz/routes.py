"""`/viz`: where the live 3D view listens (the session page embeds it), and its replay of a finished run."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, Query, Request
from pydantic import ConfigDict, Field
from sqlalchemy import select

from server.api_types import MAX_ID, IdPath, RequestModel
from server.audit import service as audit
from server.auth.access import ObjectAccess, require_object, require_patient
from server.auth.dependencies import CurrentUser, authenticated_claims, current_user
from server.auth.security import TokenClaims
from server.db import SessionDep
from server.errors import ConflictError, WorkerUnavailableError
from server.jsonable import to_jsonable
from server.patients.models import Patient
from server.patients.service import read_patient
from server.robotd.models import SessionEvent
from server.robotd.runs import get_run
from server.scheduling.models import ScheduledSession
from server.sessions.logs import telemetry_columns
from server.viz.proxy import viewer_of
from server.viz.view import LiveView, ReplayError

# The telemetry fields the console's charts draw (js/console.js), by the same names as in the live frames.
REPLAY_SERIES = ("cue_specific_force_m_s2", "stance_pose", "slider_position_m", "drive_force_n", "plate_cop_m",
                 "plate_force_z_n", "harness_load_n")  # fmt: skip

router = APIRouter(prefix="/viz", tags=["3d view"], dependencies=[Depends(current_user), ObjectAccess])

NO_VIEW = "the 3D view is not running (turned off with SSP_REHAB_VIZ_ENABLED=false, or its port was taken)"


class ReplayRequest(RequestModel):
    run_id: Annotated[int, Field(ge=1, le=MAX_ID)]

    model_config = ConfigDict(json_schema_extra={"examples": [{"run_id": 1}]})


class CameraRequest(RequestModel):
    preset: Literal["oblique", "front", "left", "right", "top"]

    model_config = ConfigDict(json_schema_extra={"examples": [{"preset": "front"}]})


class ControlsRequest(RequestModel):
    visible: bool = Field(description="Show viser's own control panel (the console's engineering switch).")

    model_config = ConfigDict(json_schema_extra={"examples": [{"visible": True}]})


class FigureRequest(RequestModel):
    patient_id: Annotated[int, Field(ge=1, le=MAX_ID, description="The figure takes this patient's height.")]

    model_config = ConfigDict(json_schema_extra={"examples": [{"patient_id": 1}]})


def _viewer(claims: Annotated[TokenClaims, Depends(authenticated_claims)]) -> str:
    return viewer_of(claims)


# The browser that asks: its own views of the 3D scene (the relay names them by the same login).
Viewer = Annotated[str, Depends(_viewer)]


def _view(request: Request) -> LiveView:
    view: LiveView | None = getattr(request.app.state, "viz", None)
    if view is None:
        raise WorkerUnavailableError(NO_VIEW)
    return view


def _patient_of_run(session: Any, run: Any) -> Patient:
    booking = session.get(ScheduledSession, run.scheduled_session_id)
    patient = session.get(Patient, booking.patient_id) if booking is not None else None
    if patient is None:
        raise ConflictError(f"session run {run.id} has lost its booking or patient")
    return patient


@router.get("")
def view_status(request: Request, viewer: Viewer) -> dict[str, Any]:
    """The view's port (the page builds `http://<this host>:<port>/`), mode (live or replay) and frames shown;
    `controls_visible` is whether viser's panel shows in the asking browser."""
    view: LiveView | None = getattr(request.app.state, "viz", None)
    if view is None:
        return {"available": False, "detail": NO_VIEW}
    return view.status(viewer)


@router.post("/replay", responses={503: {"description": "No 3D view"}, 409: {"description": "No telemetry"}})
def replay_run(
    data: ReplayRequest, request: Request, session: SessionDep, user: CurrentUser, viewer: Viewer
) -> dict[str, Any]:
    """Play a recorded run in the 3D view at its recorded speed; `POST /viz/live` returns to the robot."""
    require_object(session, user, "run_id", data.run_id)
    view = _view(request)
    run = get_run(session=session, run_id=data.run_id)
    columns = telemetry_columns(session=session, run_id=run.id)
    try:
        view.replay(run.id, columns)
        view.set_figure_height(_patient_of_run(session, run).height_m)
    except ReplayError as error:
        raise ConflictError(f"session run {run.id} cannot be replayed: {error}", field=error.field) from error
    audit.record(session=session, user_id=user.id, action="replay", resource_type="session_run", resource_id=run.id)
    session.commit()
    return view.status(viewer)


@router.post("/live", responses={503: {"description": "No 3D view"}})
def go_live(request: Request, viewer: Viewer) -> dict[str, Any]:
    """Leave replay: the view follows the robot again."""
    view = _view(request)
    view.go_live()
    return view.status(viewer)


@router.post("/camera", responses={503: {"description": "No 3D view"}})
def set_camera(data: CameraRequest, request: Request, viewer: Viewer) -> dict[str, Any]:
    """Look from a preset: front (where the patient faces), left or right side, from above, or the overview;
    in the 3D views of the asking browser only (its login), every other browser keeps its own camera."""
    view = _view(request)
    view.set_camera(viewer, data.preset)
    return view.status(viewer)


@router.post("/controls", responses={503: {"description": "No 3D view"}})
def set_controls(data: ControlsRequest, request: Request, viewer: Viewer) -> dict[str, Any]:
    """Expand or minimize viser's control panel (camera presets, viser's developer settings) in the 3D views
    of the asking browser only (its login); every other browser keeps its own."""
    view = _view(request)
    view.set_controls_visible(viewer, data.visible)
    return view.status(viewer)


@router.post("/figure", responses={503: {"description": "No 3D view"}})
def set_figure(
    data: FigureRequest, request: Request, session: SessionDep, user: CurrentUser, viewer: Viewer
) -> dict[str, Any]:
    """The standing figure takes the patient's height (the view still shows no name or other data)."""
    require_patient(session, user, data.patient_id)
    view = _view(request)
    patient = read_patient(session=session, patient_id=data.patient_id, actor_id=user.id)
    view.set_figure_height(patient.height_m)
    return view.status(viewer)


SERIES_POINTS_MAX = 4000


@router.get("/runs/{run_id}/series")
def run_series(
    run_id: IdPath,
    session: SessionDep,
    points: Annotated[int, Query(ge=10, le=SERIES_POINTS_MAX, description="At most this many samples.")] = 2000,
) -> dict[str, Any]:
    """A recorded run's signals for the console's charts during its replay, in time into the run (s; SI
    units, like the telemetry frames), evenly decimated to at most `points` samples."""
    run = get_run(session=session, run_id=run_id)
    columns = telemetry_columns(session=session, run_id=run.id)
    time_s = np.asarray(columns["time_s"], dtype=float)
    rows = np.unique(np.linspace(0, len(time_s) - 1, min(points, len(time_s))).round().astype(int))
    start = session.scalars(
        select(SessionEvent.tick_time_s).where(SessionEvent.run_id == run.id, SessionEvent.kind == "start")
    ).first()
    origin = float(start) if start is not None else float(time_s[0])
    series = {name: to_jsonable(np.asarray(columns[name])[rows]) for name in REPLAY_SERIES if name in columns}
    return {"run_id": run.id, "time_s": to_jsonable(time_s[rows] - origin), **series}
