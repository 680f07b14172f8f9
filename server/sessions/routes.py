"""Run control (`/sessions/{id}/start|pause|resume|stop`), `/estop`, the robot's state and reset, runs and
events, the telemetry WebSocket, and session-log export (per run and bulk, for studies)."""

from __future__ import annotations

import asyncio
import datetime as dt
import logging
import time
from typing import Annotated, Any, Literal

from fastapi import (
    APIRouter,
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

from server import exports
from server.api_types import MAX_ID, NO_NUL_PATTERN, IdPath
from server.audit import service as audit
from server.auth.dependencies import (
    AuthState,
    CurrentUser,
    auth_state,
    authenticated_claims,
    claims_for_token,
    current_user,
    token_from_request,
    unauthorized,
    user_for_claims,
)
from server.auth.security import TokenClaims
from server.db import Database, SessionDep, writes
from server.errors import ConflictError, NotFoundError, WorkerUnavailableError
from server.exports.dataset import dataset_zip
from server.jsonable import to_jsonable
from server.reviews.service import refuse_start_while_unacknowledged
from server.robotd.link import NO_ROBOT_PROCESS
from server.robotd.status import COMMAND_STALE_S, DAEMON_STALE_S
from server.scheduling.service import get_booking
from server.sessions import logs, service
from server.sessions.models import SessionRun
from server.sessions.schemas import EmergencyStopResult, SessionEventOut, SessionRunOut, StartCancelledOut
from server.sessions.worker import RobotLink

logger = logging.getLogger(__name__)

router = APIRouter(tags=["sessions"], dependencies=[Depends(current_user)])
# Motion commands hold no database session while the daemon works: it writes the run meanwhile.
motion_router = APIRouter(tags=["sessions"])
# The emergency stop needs no login at all: the console page must always be able to stop motion.
estop_router = APIRouter(tags=["sessions"])
websocket_router = APIRouter()

NO_ROBOT = "no robot connected: the robot daemon is not attached (records, schedules and exports still work)"
ExportFormat = Literal["csv", "parquet", "json", "c3d"]
LAST_EXPORT_DAY = dt.date.max - dt.timedelta(days=1)  # a range ends at the next day's midnight


@writes
def _audit(*, session: Session, **entry: Any) -> None:
    audit.record(session=session, **entry)


def _ready_robot(request: Request, stale_s: float) -> RobotLink:
    robot: RobotLink | None = request.app.state.robot
    if robot is None:
        raise WorkerUnavailableError(NO_ROBOT)
    robot_status = robot.status(stale_s)
    if not robot_status.ready:
        raise WorkerUnavailableError(f"robot {robot.robot!r} is {robot_status.state.label}: {robot_status.reason}")
    return robot


def require_robot(request: Request) -> RobotLink:
    """For commands: a daemon a little late with its beat (a busy machine) still gets them."""
    return _ready_robot(request, COMMAND_STALE_S)


def require_live_robot(request: Request) -> RobotLink:
    """For state reads: as strict as /health, so a dead or hung daemon is never shown as alive."""
    return _ready_robot(request, DAEMON_STALE_S)


RobotDep = Annotated[RobotLink, Depends(require_robot)]
LiveRobotDep = Annotated[RobotLink, Depends(require_live_robot)]


@estop_router.post(
    "/estop",
    response_model=EmergencyStopResult,
    responses={503: {"description": "No robot process received the stop: the drives stop on their own heartbeat loss"}},
)
async def emergency_stop(request: Request) -> EmergencyStopResult:
    """Anyone at the console, logged in or not, always, one call. The first statement latches the stop in
    the worker's shared memory, before any await, lock, database work or message; the answer is 200 only
    once the worker confirms it. Who asked is audited afterwards, truthfully (unauthenticated included)."""
    robot: RobotLink | None = request.app.state.robot
    sequence = robot.emergency_stop() if robot is not None else None
    latched_ns = time.perf_counter_ns()
    token = token_from_request(request, auth_state(request).cookie_name)
    confirmed = robot is not None and await robot.estop_confirmed(sequence)
    asyncio.get_running_loop().run_in_executor(
        None, _record_emergency_stop, request.app.state.database, auth_state(request), robot, token, confirmed
    )
    if not confirmed:
        why = robot.status().reason if robot is not None else "this console runs without a robot"
        raise WorkerUnavailableError(f"{NO_ROBOT_PROCESS} ({why})")
    return EmergencyStopResult(
        status="emergency stop latched by the robot",
        utc=dt.datetime.now(dt.UTC),
        confirmed_after_ms=round((time.perf_counter_ns() - latched_ns) * 1e-6, 3),
    )


def _credential(database: Database, state: AuthState, token: str | None) -> tuple[int | None, str]:
    """(user id, what the request proved): a user only for a valid, unrevoked login of an active account."""
    if not token:
        return None, "none"
    claims = claims_for_token(token, state)
    if claims is None:
        return None, "invalid, expired or revoked token"
    with database.session() as session:
        user = user_for_claims(session, claims)
        return (user.id, "login session") if user is not None else (None, "ended login session or inactive account")


def _record_emergency_stop(
    database: Database, state: AuthState, robot: RobotLink | None, token: str | None, confirmed: bool
) -> None:
    try:
        user_id, credential = _credential(database, state, token)
        if confirmed and robot is not None:
            try:
                robot.note_emergency_stop(user_id, user_id is not None, credential)
                return
            except Exception:
                logger.exception("the robot daemon did not take the emergency stop's record; the console keeps it")
        credential += "" if confirmed else "; not received: no robot process"
        with database.session() as session:
            service.record_emergency_stop(
                session=session,
                user_id=user_id,
                authenticated=user_id is not None,
                credential=credential,
                run_ids=[],
                clock=service.NO_CLOCK,
            )
    except Exception:
        logger.exception("the emergency stop could not be audited")


def acting_user_id(request: Request, claims: Annotated[TokenClaims, Depends(authenticated_claims)]) -> int:
    """The logged-in user, checked in a database session of its own that ends before the command."""
    database: Database = request.app.state.database
    with database.session() as session:
        user = user_for_claims(session, claims)
        if user is None:
            raise unauthorized("login session ended: log in again")
        return user.id


ActingUserId = Annotated[int, Depends(acting_user_id)]


def _run_out(request: Request, run_id: int) -> SessionRunOut:
    database: Database = request.app.state.database
    with database.session() as session:
        return SessionRunOut.model_validate(service.get_run(session=session, run_id=run_id))


@motion_router.post(
    "/sessions/{session_id}/start", response_model=SessionRunOut, responses={503: {"description": "No robot"}}
)
def start_session(session_id: IdPath, request: Request, user_id: ActingUserId, robot: RobotDep) -> SessionRunOut:
    """The robot daemon checks the booking, plans and checks its prescription version, starts motion and
    records a new run (with the run id it chose). Refused (409) while the robot's last run ended in a stop
    that moved the patient (emergency stop, interruption, fault, fall, limit stop) nobody acknowledged."""
    database: Database = request.app.state.database
    with database.session() as session:  # closed before the daemon writes the run (SQLite has one writer)
        refuse_start_while_unacknowledged(session=session, session_id=session_id)
    return _run_out(request, robot.start_session(session_id, user_id))


def _control(command: service.RunCommand) -> Any:
    def control(
        session_id: IdPath, request: Request, user_id: ActingUserId, robot: RobotDep
    ) -> SessionRunOut | StartCancelledOut:
        run_id = robot.control(session_id, command, user_id)
        if run_id is None:  # a stop while the session's start was still loading cancelled that start
            return StartCancelledOut(
                scheduled_session_id=session_id,
                detail=f"the start of session {session_id} was still loading: it is cancelled and nothing moved",
            )
        return _run_out(request, run_id)

    control.__name__ = f"{command}_session"
    control.__doc__ = f"{command.capitalize()} the active run of this session."
    return control


for _command in ("pause", "resume", "stop"):
    motion_router.add_api_route(
        f"/sessions/{{session_id}}/{_command}",
        _control(_command),
        methods=["POST"],
        response_model=SessionRunOut | StartCancelledOut,
        responses={503: {"description": "No robot"}, 409: {"description": "Not in a state that allows it"}},
    )


@router.get("/robot/state", responses={503: {"description": "No robot, or its daemon is starting, faulted or gone"}})
def robot_state(robot: LiveRobotDep) -> dict[str, Any]:
    """The worker's latest state: supervisor state, stance pose, slider positions, drive forces, tick stats,
    and the robot daemon's own status."""
    state: dict[str, Any] = to_jsonable(robot.latest_state())
    state["robot"] = robot.status().to_dict()
    return state


@motion_router.post(
    "/robot/reset",
    responses={503: {"description": "No robot"}, 409: {"description": "Nothing to reset (not stopped or faulted)"}},
)
def reset_robot(user_id: ActingUserId, robot: RobotDep) -> dict[str, str]:
    """Clears a latched emergency stop or fault. Never restarts motion."""
    robot.reset(user_id)
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
    selection = {"from_date": str(from_date), "to_date": str(to_date), "diagnosis": diagnosis}
    try:
        study = [_log_for_run(request, session, r, False, include_free_text) for r, _ in rows]
        if layout == "parquet_dataset":
            bundle = dataset_zip(study, selection=selection)
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
    fanout = websocket.app.state.fanout
    if fanout is None:
        await websocket.send_json({"type": "error", "detail": NO_ROBOT})
        await websocket.close(code=status.WS_1013_TRY_AGAIN_LATER, reason="no robot connected")
        return
    queue = fanout.subscribe()
    try:
        while True:
            await websocket.send_text(await queue.get())
    except (WebSocketDisconnect, RuntimeError):
        pass  # the client went away
    finally:
        fanout.unsubscribe(queue)
