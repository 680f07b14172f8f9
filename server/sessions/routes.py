"""Run control (`/sessions/{id}/start|pause|resume|stop`), `/estop`, the robot's state and reset, runs and
events, the telemetry WebSocket, and session-log export (per run and bulk, for studies)."""

from __future__ import annotations

import datetime as dt
import importlib
import logging
from types import ModuleType
from typing import Annotated, Any, Literal

from fastapi import (
    APIRouter,
    BackgroundTasks,
    Depends,
    HTTPException,
    Query,
    Request,
    Response,
    WebSocket,
    WebSocketDisconnect,
    status,
)
from fastapi.concurrency import run_in_threadpool
from sqlalchemy import select
from sqlalchemy.orm import Session

from server.api_types import MAX_ID, NO_NUL_PATTERN, IdPath
from server.audit import service as audit
from server.auth.dependencies import (
    CurrentUser,
    auth_state,
    authenticated_claims,
    claims_for_token,
    current_user,
    token_from_request,
    user_for_claims,
)
from server.auth.security import TokenClaims
from server.db import Database, SessionDep, writes
from server.errors import ConflictError, NotFoundError, WorkerUnavailableError
from server.jsonable import to_jsonable
from server.reviews.service import refuse_start_while_unacknowledged
from server.scheduling.service import get_booking
from server.sessions import logs, service
from server.sessions.models import SessionRun
from server.sessions.schemas import EmergencyStopResult, SessionEventOut, SessionRunOut
from server.sessions.worker import WorkerControl

logger = logging.getLogger(__name__)

router = APIRouter(tags=["sessions"], dependencies=[Depends(current_user)])
# The emergency stop checks the token without the database (server.auth.dependencies).
estop_router = APIRouter(tags=["sessions"])
websocket_router = APIRouter()

NO_ROBOT = "no robot connected: the real-time worker is not running (records, schedules and exports still work)"
ExportFormat = Literal["csv", "parquet", "json", "c3d"]
LAST_EXPORT_DAY = dt.date.max - dt.timedelta(days=1)  # a range ends at the next day's midnight


@writes
def _audit(*, session: Session, **entry: Any) -> None:
    audit.record(session=session, **entry)


def require_worker(request: Request) -> WorkerControl:
    worker: WorkerControl | None = request.app.state.worker
    if worker is None:
        raise WorkerUnavailableError(NO_ROBOT)
    return worker


WorkerDep = Annotated[WorkerControl, Depends(require_worker)]


@estop_router.post("/estop", response_model=EmergencyStopResult, responses={503: {"description": "No robot"}})
async def emergency_stop(
    request: Request, background: BackgroundTasks, claims: Annotated[TokenClaims, Depends(authenticated_claims)]
) -> EmergencyStopResult:
    """Any authenticated user, always, one call. Runs on the event loop and reaches the worker before any
    database work (that is recorded afterwards), so a busy service cannot delay it."""
    worker: WorkerControl | None = request.app.state.worker
    if worker is None:
        raise WorkerUnavailableError(NO_ROBOT)
    worker.emergency_stop()
    recorder = request.app.state.recorder
    if recorder is not None:
        recorder.end_run_after_tail()
    database: Database = request.app.state.database
    background.add_task(_record_emergency_stop, database, claims.user_id, worker)
    return EmergencyStopResult(status="emergency stop sent to the robot", utc=dt.datetime.now(dt.UTC))


def _record_emergency_stop(database: Database, user_id: int, worker: WorkerControl) -> None:
    with database.session() as session:
        service.record_emergency_stop(session=session, user_id=user_id, worker=worker)


@router.post("/sessions/{session_id}/start", response_model=SessionRunOut, responses={503: {"description": "No robot"}})
def start_session(
    session_id: IdPath, request: Request, session: SessionDep, user: CurrentUser, worker: WorkerDep
) -> SessionRunOut:
    """Loads the session's prescription version into the worker and starts motion; records a new run.
    Refused (409) while the robot's last run ended in an unacknowledged fall, fault or limit stop."""
    refuse_start_while_unacknowledged(session=session, session_id=session_id)
    run = service.start_run(
        session=session, session_id=session_id, worker=worker, actor_id=user.id, recorder=request.app.state.recorder
    )
    return SessionRunOut.model_validate(run)


def _control(command: service.RunCommand) -> Any:
    def control(
        session_id: IdPath, request: Request, session: SessionDep, user: CurrentUser, worker: WorkerDep
    ) -> SessionRunOut:
        run = service.control_run(
            session=session, session_id=session_id, command=command, worker=worker, actor_id=user.id
        )
        if command == "stop" and request.app.state.recorder is not None:
            request.app.state.recorder.end_run_after_tail()
        return SessionRunOut.model_validate(run)

    control.__name__ = f"{command}_session"
    control.__doc__ = f"{command.capitalize()} the active run of this session."
    return control


for _command in ("pause", "resume", "stop"):
    router.add_api_route(
        f"/sessions/{{session_id}}/{_command}",
        _control(_command),
        methods=["POST"],
        response_model=SessionRunOut,
        responses={503: {"description": "No robot"}, 409: {"description": "Not in a state that allows it"}},
    )


@router.get("/robot/state", responses={503: {"description": "No robot"}})
def robot_state(worker: WorkerDep) -> dict[str, Any]:
    """The worker's latest state: supervisor state, stance pose, slider positions, drive forces, tick stats."""
    state: dict[str, Any] = to_jsonable(worker.latest_state())
    return state


@router.post(
    "/robot/reset",
    responses={503: {"description": "No robot"}, 409: {"description": "Nothing to reset (not stopped or faulted)"}},
)
def reset_robot(session: SessionDep, user: CurrentUser, worker: WorkerDep) -> dict[str, str]:
    """Clears a latched emergency stop or fault. Never restarts motion."""
    try:
        worker.reset()
    except Exception as error:  # the worker's refusal (e.g. reset while idle) is the client's conflict
        raise service.refused(error) from error
    service.record_robot_command(session=session, user_id=user.id, command="reset", worker=worker)
    return {"status": "reset sent to the robot"}


@router.get("/sessions/{session_id}/runs", response_model=list[SessionRunOut])
def list_runs(session_id: IdPath, session: SessionDep) -> list[SessionRunOut]:
    return [SessionRunOut.model_validate(r) for r in service.runs_of_booking(session=session, session_id=session_id)]


@router.get("/runs/{run_id}", response_model=SessionRunOut)
def get_run(run_id: IdPath, session: SessionDep) -> SessionRunOut:
    return SessionRunOut.model_validate(service.get_run(session=session, run_id=run_id))


@router.get("/runs/{run_id}/events", response_model=list[SessionEventOut])
def list_events(run_id: IdPath, session: SessionDep) -> list[SessionEventOut]:
    return [SessionEventOut.model_validate(e) for e in service.events_of_run(session=session, run_id=run_id)]


# --- export --------------------------------------------------------------------------------------


def _exports() -> ModuleType:
    try:
        return importlib.import_module("server.exports")
    except ImportError as error:
        raise HTTPException(status.HTTP_501_NOT_IMPLEMENTED, detail="export formats are not installed") from error


def _log_for_run(request: Request, session: Any, run_id: int, identify: bool, include_free_text: bool = False) -> Any:
    return logs.session_log(
        session=session,
        run_id=run_id,
        twin=request.app.state.twin,
        salt=request.app.state.pseudonym_key,
        identify=identify,
        include_free_text=include_free_text,
    )


@router.get(
    "/sessions/{session_id}/export",
    response_class=Response,
    responses={200: {"content": {"application/octet-stream": {}}, "description": "The run's session log"}},
)
def export_session(
    session_id: IdPath,
    request: Request,
    session: SessionDep,
    user: CurrentUser,
    export_format: Annotated[ExportFormat, Query(alias="format")] = "csv",
    run_id: Annotated[int | None, Query(ge=1, le=MAX_ID, description="Default: the latest run.")] = None,
    identify: Annotated[bool, Query(description="Include name and record number (admin only).")] = False,
) -> Response:
    """One self-describing bundle of a session run: telemetry, events and a metadata sidecar."""
    if identify and user.role != "admin":
        raise HTTPException(status.HTTP_403_FORBIDDEN, detail="identify = true: needs the admin role")
    booking = get_booking(session=session, session_id=session_id)
    query = select(SessionRun).where(SessionRun.scheduled_session_id == booking.id).order_by(SessionRun.id.desc())
    if run_id is not None:
        query = query.where(SessionRun.id == run_id)
    run = session.scalars(query.limit(1)).first()
    if run is None:
        raise NotFoundError(f"session {session_id} run", run_id if run_id is not None else "(any)")
    exports = _exports()
    try:
        body, media_type, filename = exports.export_session(
            _log_for_run(request, session, run.id, identify), export_format
        )
    except exports.SessionLogError as error:
        raise ConflictError(f"session run {run.id} cannot be exported: {error}", field=error.field) from error
    _audit(
        session=session,
        user_id=user.id,
        action="export",
        resource_type="session_run",
        resource_id=run.id,
        details={"patient_id": booking.patient_id, "format": export_format, "identified": identify},
    )
    return Response(body, media_type=media_type, headers={"Content-Disposition": f'attachment; filename="{filename}"'})


@router.get(
    "/exports/bulk",
    response_class=Response,
    responses={200: {"content": {"application/zip": {}}, "description": "Zip of pseudonymised session logs"}},
)
def export_study(
    request: Request,
    session: SessionDep,
    user: CurrentUser,
    from_date: Annotated[dt.date, Query(le=LAST_EXPORT_DAY)],
    to_date: Annotated[dt.date, Query(le=LAST_EXPORT_DAY)],
    diagnosis: Annotated[str | None, Query(max_length=200, pattern=NO_NUL_PATTERN)] = None,
    layout: Annotated[
        Literal["folders", "parquet_dataset"],
        Query(description="folders: a folder per run; parquet_dataset: hive-partitioned Parquet (docs/exports.md)."),
    ] = "folders",
    include_free_text: Annotated[bool, Query(description="Keep the free-text diagnosis and notes.")] = False,
) -> Response:
    """Pseudonymised session logs of every recorded run started from `from_date` to `to_date` (UTC days)."""
    rows = logs.study_run_ids(session=session, start=from_date, end=to_date, diagnosis=diagnosis)
    if not rows:
        raise NotFoundError("recorded session runs in that range", f"{from_date}..{to_date}")
    exports = _exports()
    selection: dict[str, Any] = {
        "from_date": str(from_date),
        "to_date": str(to_date),
        "diagnosis": diagnosis,
        "include_free_text": include_free_text,
    }
    try:
        study = [_log_for_run(request, session, r, False, include_free_text) for r, _ in rows]
        if layout == "parquet_dataset":
            bundle = importlib.import_module("server.exports.dataset").dataset_zip(study, selection=selection)
        else:
            bundle = exports.export_bundle(study, selection=selection)
    except exports.SessionLogError as error:
        raise ConflictError(f"the study bundle cannot be exported: {error}", field=error.field) from error
    _audit(
        session=session,
        user_id=user.id,
        action="export",
        resource_type="study",
        details={
            "run_ids": [r for r, _ in rows],
            "patient_ids": sorted({p for _, p in rows}),
            "layout": layout,
            "free_text": include_free_text,
        },
    )
    filename = f"ssp-rehab-study-{from_date}-{to_date}{'-parquet' if layout == 'parquet_dataset' else ''}.zip"
    return Response(
        bundle, media_type="application/zip", headers={"Content-Disposition": f'attachment; filename="{filename}"'}
    )


# --- telemetry WebSocket ---------------------------------------------------------------------------


def _authorise_watch(database: Database, claims: TokenClaims | None, session_id: int) -> str | None:
    """None when the user may watch this session; else the reason to refuse."""
    if claims is None:
        return "not authenticated"
    with database.session() as session:
        user = user_for_claims(session, claims)
        if user is None:
            return "login session ended"
        try:
            booking = get_booking(session=session, session_id=session_id)
        except NotFoundError as error:
            return str(error)
        _audit(
            session=session,
            user_id=user.id,
            action="watch",
            resource_type="scheduled_session",
            resource_id=session_id,
            details={"patient_id": booking.patient_id},
        )
    return None


@websocket_router.websocket("/sessions/{session_id}/telemetry")
async def telemetry(websocket: WebSocket, session_id: int) -> None:
    """About 30 frames/s of the robot's latest state and telemetry sample while this session is watched.
    Authenticates with the session cookie, a bearer header or `?token=`."""
    state = auth_state(websocket)
    token = token_from_request(websocket, state.cookie_name) or websocket.query_params.get("token")
    claims = claims_for_token(token, state)
    refusal: str | None = "unknown session"
    if 1 <= session_id <= MAX_ID:
        refusal = await run_in_threadpool(_authorise_watch, websocket.app.state.database, claims, session_id)
    if refusal is not None:
        await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason=refusal)
        return
    await websocket.accept()
    recorder = websocket.app.state.recorder
    if recorder is None:
        await websocket.send_json({"type": "error", "detail": NO_ROBOT})
        await websocket.close(code=status.WS_1013_TRY_AGAIN_LATER, reason="no robot connected")
        return
    queue = recorder.subscribe()
    try:
        while True:
            await websocket.send_text(await queue.get())
    except (WebSocketDisconnect, RuntimeError):
        pass  # the client went away
    finally:
        recorder.unsubscribe(queue)
