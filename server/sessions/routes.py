"""Run control (`/sessions/{id}/start|pause|resume|stop`), `/estop`, the robot's state and reset, runs and
events, the telemetry WebSocket, and session-log export (per run and bulk, for studies)."""

from __future__ import annotations

import asyncio
import contextlib
import datetime as dt
import logging
import time
from typing import Annotated, Any, Literal

from fastapi import (
    APIRouter,
    Depends,
    HTTPException,
    Path,
    Query,
    Request,
    Response,
    WebSocket,
    WebSocketDisconnect,
    status,
)
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse
from sqlalchemy import func, select
from sqlalchemy.exc import OperationalError
from sqlalchemy.orm import Session

from server import exports
from server.api_types import MAX_ID, NO_NUL_PATTERN, IdPath
from server.audit import service as audit
from server.auth.access import ObjectAccess, object_access_own_session, patients_in_care, require_object
from server.auth.dependencies import (
    AuthState,
    auth_state,
    authenticated_claims,
    claims_for_token,
    credential_of,
    current_user,
    token_from_request,
    unauthorized,
    user_for_claims,
)
from server.auth.live import LOGIN_RECHECK_S, ended_here, ended_in_database
from server.auth.safe_commands import SafeCommandUser
from server.auth.security import TokenClaims
from server.db import Database, SessionDep, get_session, writes
from server.errors import NotFoundError, WorkerUnavailableError
from server.exports.jobs import ExportJob, ExportJobs, ExportResponse
from server.exports.log import to_json
from server.jsonable import to_jsonable
from server.reviews.service import refuse_start_while_unacknowledged
from server.robotd import estop, runs
from server.robotd.estop import NO_ROBOT_PROCESS
from server.robotd.interfaces import RobotLink
from server.robotd.models import SessionRun
from server.robotd.status import COMMAND_STALE_S, DAEMON_STALE_S
from server.scheduling.service import get_booking
from server.sessions import logs
from server.sessions.schemas import EmergencyStopResult, SessionEventOut, SessionRunOut, StartCancelledOut
from server.users.models import User

logger = logging.getLogger(__name__)

router = APIRouter(tags=["sessions"], dependencies=[Depends(current_user), ObjectAccess])
# Motion commands hold no database session while the daemon works: it writes the run meanwhile.
motion_router = APIRouter(tags=["sessions"])
# The emergency stop needs no login at all: the console page must always be able to stop motion.
estop_router = APIRouter(tags=["sessions"])
websocket_router = APIRouter()
# Exports stream after the route returns: their database session and login check end before the response
# (scope "function"), so no request holds a connection while an export process builds the file.
export_router = APIRouter(tags=["exports"])

NO_ROBOT_HERE = "this console runs without a robot"
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
    responses={
        503: {
            "description": "No robot process received the stop (the daemon or its worker is gone): the drives "
            "stop on their own heartbeat loss"
        },
        504: {
            "description": "Requested, not confirmed in time: the worker is alive but slow or stopped; the stop "
            "stays requested and latches when it next runs"
        },
        409: {"description": "The robot daemon is starting: no worker runs yet, so nothing moves"},
    },
)
async def emergency_stop(request: Request) -> Any:
    """Anyone at the console, logged in or not, always, one call. For scripts: the console page uses the
    robot's stop listener, which no web work can hold up (server/robotd/estop_listener.py). The first
    statement latches the stop in the worker's shared memory, before any await, lock, database work or
    message; the answer is 200 only once the worker confirms it. Who asked is audited afterwards, truthfully
    (unauthenticated included)."""
    robot: RobotLink | None = request.app.state.robot
    sequence = robot.emergency_stop() if robot is not None else None
    latched_ns = time.perf_counter_ns()
    token = token_from_request(request, auth_state(request).cookie_name)
    if robot is not None and await robot.estop_confirmed(sequence):
        answer = estop.confirmed(latched_ns)
    elif robot is not None:
        answer = robot.unconfirmed_stop()
    else:
        answer = estop.StopAnswer(
            estop.StopOutcome.NO_DAEMON, f"{NO_ROBOT_PROCESS} (this console runs without a robot)"
        )
    asyncio.get_running_loop().run_in_executor(
        None, _record_emergency_stop, request.app.state.database, auth_state(request), robot, token, answer
    )
    if answer.outcome is estop.StopOutcome.CONFIRMED:
        return EmergencyStopResult(
            status=estop.ESTOP_LATCHED, utc=dt.datetime.now(dt.UTC), confirmed_after_ms=answer.confirmed_after_ms
        )
    return JSONResponse(answer.body(), status_code=answer.http_status)


def _record_emergency_stop(
    database: Database, state: AuthState, robot: RobotLink | None, token: str | None, answer: estop.StopAnswer
) -> None:
    try:
        user_id, credential = credential_of(database, claims_for_token(token, state), bool(token))
        if answer.outcome is not estop.StopOutcome.CONFIRMED:
            credential += f"; not confirmed by the worker ({answer.outcome.value})"
        if robot is not None and answer.outcome is not estop.StopOutcome.NO_DAEMON:
            try:  # the daemon records it and ends the run (a slow one when it runs again)
                robot.note_emergency_stop(user_id, user_id is not None, credential)
                return
            except Exception:
                logger.exception("the robot daemon did not take the emergency stop's record; the console keeps it")
        with database.session() as session:
            runs.record_emergency_stop(
                session=session,
                user_id=user_id,
                authenticated=user_id is not None,
                credential=credential,
                run_ids=[],
                clock=runs.NO_CLOCK,
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
        return SessionRunOut.model_validate(runs.get_run(session=session, run_id=run_id))


# Starting or resuming motion needs the patient in the caller's care; pause and stop never ask (a stop is
# never refused). A separate dependency, in its own database session, so that it composes with however the
# motion routes authenticate.
IN_CARE_FOR_MOTION = [Depends(object_access_own_session)]


@motion_router.post(
    "/sessions/{session_id}/start",
    response_model=SessionRunOut,
    responses={503: {"description": "No robot"}},
    dependencies=IN_CARE_FOR_MOTION,
)
def start_session(session_id: IdPath, request: Request, user_id: ActingUserId, robot: RobotDep) -> SessionRunOut:
    """The robot daemon checks the booking, plans and checks its prescription version, starts motion and
    records a new run (with the run id it chose). Refused (409) while the robot's last run ended in a stop
    that moved the patient (emergency stop, interruption, fault, fall, limit stop) nobody acknowledged."""
    database: Database = request.app.state.database
    with database.session() as session:  # closed before the daemon writes the run (SQLite has one writer)
        refuse_start_while_unacknowledged(session=session, session_id=session_id)
    return _run_out(request, robot.start_session(session_id, user_id))


def _control(command: runs.RunCommand) -> Any:
    def answer(session_id: int, run: dict[str, Any] | None) -> SessionRunOut | StartCancelledOut:
        if run is None:  # a stop while the session's start was still loading cancelled that start
            return StartCancelledOut(
                scheduled_session_id=session_id,
                detail=f"the start of session {session_id} was still loading: it is cancelled and nothing moved",
            )
        return SessionRunOut.model_validate(run)

    if command == "resume":  # motion again: a login the database confirms, as for a start

        def control(session_id: IdPath, user_id: ActingUserId, robot: RobotDep) -> SessionRunOut | StartCancelledOut:
            return answer(session_id, robot.control(session_id, command, user_id))

    else:  # stop and pause only make the robot safer: they never wait for the database

        def control(  # type: ignore[misc]
            session_id: IdPath, login: SafeCommandUser, robot: RobotDep
        ) -> SessionRunOut | StartCancelledOut:
            return answer(session_id, robot.control(session_id, command, login.user_id, login.credential))

    control.__name__ = f"{command}_session"
    control.__doc__ = (
        f"{command.capitalize()} the active run of this session. The answer is the robot daemon's record of the run."
    )
    return control


for _command in ("pause", "resume", "stop"):
    motion_router.add_api_route(
        f"/sessions/{{session_id}}/{_command}",
        _control(_command),
        methods=["POST"],
        response_model=SessionRunOut | StartCancelledOut,
        responses={503: {"description": "No robot"}, 409: {"description": "Not in a state that allows it"}},
        dependencies=IN_CARE_FOR_MOTION if _command == "resume" else None,
    )


@motion_router.get(
    "/robot/state", responses={503: {"description": "No robot, or its daemon is starting, faulted or gone"}}
)
def robot_state(_login: SafeCommandUser, robot: LiveRobotDep) -> dict[str, Any]:
    """The worker's latest state: supervisor state, stance pose, slider positions, drive forces, tick stats,
    and the robot daemon's own status. Read from the robot, never from the database."""
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
    return [SessionRunOut.model_validate(r) for r in runs.runs_of_booking(session=session, session_id=session_id)]


@router.get("/runs/{run_id}", response_model=SessionRunOut)
def get_run(run_id: IdPath, session: SessionDep) -> SessionRunOut:
    return SessionRunOut.model_validate(runs.get_run(session=session, run_id=run_id))


@router.get("/runs/{run_id}/events", response_model=list[SessionEventOut])
def list_events(run_id: IdPath, session: SessionDep) -> list[SessionEventOut]:
    return [SessionEventOut.model_validate(e) for e in runs.events_of_run(session=session, run_id=run_id)]


# --- export --------------------------------------------------------------------------------------
# Built by export processes and streamed (docs/exports.md "Streaming and jobs"): the GET routes stream at once
# (for scripts), the POST …/jobs routes start a job whose progress `GET /exports/jobs/{id}` shows.


ExportSessionDep = Annotated[Session, Depends(get_session, scope="function")]


def export_user(session: ExportSessionDep, claims: Annotated[TokenClaims, Depends(authenticated_claims)]) -> User:
    return current_user(session, claims)


ExportUser = Annotated[User, Depends(export_user)]


def export_jobs(request: Request) -> ExportJobs:
    jobs: ExportJobs = request.app.state.export_jobs
    return jobs


def _feed_runs(request: Request, run_ids: list[int], identify: bool, include_free_text: bool) -> Any:
    """The export's feed: each run's header and stored telemetry chunks, read in the feeder thread, one
    database session per run."""
    database: Database = request.app.state.database
    twin, salt = request.app.state.twin, request.app.state.pseudonym_key

    def feed(send: Any) -> None:
        for run_id in run_ids:
            with database.session() as session:
                header = logs.run_header(
                    session=session, run_id=run_id, twin=twin, salt=salt, identify=identify,
                    include_free_text=include_free_text,
                )  # fmt: skip
                send(b"R", to_json(header).encode())
                for blob in logs.telemetry_blobs(session=session, run_id=run_id):
                    send(b"C", blob)
                send(b"E", b"")

    return feed


def _session_export_job(
    request: Request, session: Session, user: User, session_id: int, export_format: str,
    run_id: int | None, identify: bool,
) -> ExportJob:  # fmt: skip
    if identify and user.role != "admin":
        raise HTTPException(status.HTTP_403_FORBIDDEN, detail="identify = true: needs the admin role")
    require_object(session, user, "session_id", session_id)  # the export router streams: no ObjectAccess
    booking = get_booking(session=session, session_id=session_id)
    query = select(SessionRun).where(SessionRun.scheduled_session_id == booking.id).order_by(SessionRun.id.desc())
    if run_id is not None:
        query = query.where(SessionRun.id == run_id)
    run = session.scalars(query.limit(1)).first()
    if run is None:
        raise NotFoundError(f"session {session_id} run", run_id if run_id is not None else "(any)")
    _audit(
        session=session,
        user_id=user.id,
        action="export",
        resource_type="session_run",
        resource_id=run.id,
        details={"patient_id": booking.patient_id, "format": export_format, "identified": identify},
    )
    _, media_type, suffix = exports.EXPORT_FORMATS[export_format]
    job = ExportJob(
        owner_id=user.id,
        spec={"kind": "session", "format": export_format},
        feed=_feed_runs(request, [run.id], identify, False),
        filename=f"session-run-{run.id}{suffix}",
        media_type=media_type,
        total_samples=run.sample_count,
        description=f"run {run.id} as {export_format}",
    )
    return export_jobs(request).submit(job)


@export_router.get(
    "/sessions/{session_id}/export",
    response_class=Response,
    responses={
        200: {"content": {"application/octet-stream": {}}, "description": "The run's session log, streamed"},
        409: {"description": "The export failed before its first byte; `detail` says why"},
    },
)
def export_session(
    session_id: IdPath,
    request: Request,
    session: ExportSessionDep,
    user: ExportUser,
    export_format: Annotated[ExportFormat, Query(alias="format")] = "csv",
    run_id: Annotated[int | None, Query(ge=1, le=MAX_ID, description="Default: the latest run.")] = None,
    identify: Annotated[bool, Query(description="Include name and record number (admin only).")] = False,
) -> Response:
    """One self-describing bundle of a session run: telemetry, events and a metadata sidecar, streamed as an
    export process builds it."""
    job = _session_export_job(request, session, user, session_id, export_format, run_id, identify)
    return ExportResponse(export_jobs(request), job, "the session run cannot be exported")


@export_router.post("/sessions/{session_id}/export/jobs", status_code=status.HTTP_202_ACCEPTED)
def start_session_export(
    session_id: IdPath,
    request: Request,
    session: ExportSessionDep,
    user: ExportUser,
    export_format: Annotated[ExportFormat, Query(alias="format")] = "csv",
    run_id: Annotated[int | None, Query(ge=1, le=MAX_ID, description="Default: the latest run.")] = None,
    identify: Annotated[bool, Query(description="Include name and record number (admin only).")] = False,
) -> dict[str, Any]:
    """Start the run's export as a job: follow it at `GET /exports/jobs/{id}`, fetch it at …/download."""
    job = _session_export_job(request, session, user, session_id, export_format, run_id, identify)
    return job.status()


def _study_export_job(
    request: Request, session: Session, user: User, from_date: dt.date, to_date: dt.date,
    diagnosis: str | None, layout: str, include_free_text: bool,
) -> ExportJob:  # fmt: skip
    rows = logs.study_run_ids(session=session, start=from_date, end=to_date, diagnosis=diagnosis)
    in_care = patients_in_care(session, user, {p for _, p in rows})
    rows = [(r, p) for r, p in rows if p in in_care]
    if not rows:
        raise NotFoundError("recorded session runs in that range", f"{from_date}..{to_date}")
    run_ids = [r for r, _ in rows]
    total = session.scalar(select(func.sum(SessionRun.sample_count)).where(SessionRun.id.in_(run_ids))) or 0
    _audit(
        session=session,
        user_id=user.id,
        action="export",
        resource_type="study",
        details={
            "run_ids": run_ids,
            "patient_ids": sorted({p for _, p in rows}),
            "layout": layout,
            "free_text": include_free_text,
        },
    )
    selection = {"from_date": str(from_date), "to_date": str(to_date), "diagnosis": diagnosis}
    job = ExportJob(
        owner_id=user.id,
        spec={"kind": "study", "layout": layout, "selection": selection},
        feed=_feed_runs(request, run_ids, False, include_free_text),
        filename=f"ssp-rehab-study-{from_date}-{to_date}{'-parquet' if layout == 'parquet_dataset' else ''}.zip",
        media_type="application/zip",
        total_samples=int(total),
        description=f"study {from_date}..{to_date}: {len(run_ids)} runs ({layout})",
    )
    return export_jobs(request).submit(job)


StudyLayout = Annotated[
    Literal["folders", "parquet_dataset"],
    Query(description="folders: a folder per run; parquet_dataset: hive-partitioned Parquet (docs/exports.md)."),
]


@export_router.get(
    "/exports/bulk",
    response_class=Response,
    responses={
        200: {"content": {"application/zip": {}}, "description": "Zip of pseudonymised session logs, streamed"},
        409: {"description": "The export failed before its first byte; `detail` says why"},
    },
)
def export_study(
    request: Request,
    session: ExportSessionDep,
    user: ExportUser,
    from_date: Annotated[dt.date, Query(le=LAST_EXPORT_DAY)],
    to_date: Annotated[dt.date, Query(le=LAST_EXPORT_DAY)],
    diagnosis: Annotated[str | None, Query(max_length=200, pattern=NO_NUL_PATTERN)] = None,
    layout: StudyLayout = "folders",
    include_free_text: Annotated[bool, Query(description="Keep the free-text diagnosis and notes.")] = False,
) -> Response:
    """Pseudonymised session logs of every recorded run started from `from_date` to `to_date` (UTC days),
    streamed as a zip while an export process builds it."""
    job = _study_export_job(request, session, user, from_date, to_date, diagnosis, layout, include_free_text)
    return ExportResponse(export_jobs(request), job, "the study bundle cannot be exported")


@export_router.post("/exports/bulk/jobs", status_code=status.HTTP_202_ACCEPTED)
def start_study_export(
    request: Request,
    session: ExportSessionDep,
    user: ExportUser,
    from_date: Annotated[dt.date, Query(le=LAST_EXPORT_DAY)],
    to_date: Annotated[dt.date, Query(le=LAST_EXPORT_DAY)],
    diagnosis: Annotated[str | None, Query(max_length=200, pattern=NO_NUL_PATTERN)] = None,
    layout: StudyLayout = "folders",
    include_free_text: Annotated[bool, Query(description="Keep the free-text diagnosis and notes.")] = False,
) -> dict[str, Any]:
    """Start the study export as a job: follow it at `GET /exports/jobs/{id}`, fetch it at …/download."""
    job = _study_export_job(request, session, user, from_date, to_date, diagnosis, layout, include_free_text)
    return job.status()


def _own_job(request: Request, job_id: str, user: User) -> ExportJob:
    job = export_jobs(request).get(job_id, user.id)
    if job is None:
        raise NotFoundError("export job", job_id)
    return job


@export_router.get("/exports/jobs/{job_id}")
def export_job_status(
    job_id: Annotated[str, Path(pattern=r"^[0-9a-f]{32}$")], request: Request, user: ExportUser
) -> dict[str, Any]:
    """state (queued | running | done | failed), fraction 0–1, bytes written so far, and why it failed."""
    return _own_job(request, job_id, user).status()


@export_router.get("/exports/jobs/{job_id}/download", response_class=Response)
def download_export_job(
    job_id: Annotated[str, Path(pattern=r"^[0-9a-f]{32}$")], request: Request, user: ExportUser
) -> Response:
    """The job's file, streamed from its first byte while the job still runs; 409 if it failed first."""
    job = _own_job(request, job_id, user)
    return ExportResponse(export_jobs(request), job, "the export failed")


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
            require_object(session, user, "session_id", session_id)
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
    assert claims is not None  # _authorise_watch refused otherwise
    queue = fanout.subscribe()
    try:
        await _send_while_logged_in(websocket, queue, state, claims)
    except (WebSocketDisconnect, RuntimeError):
        pass  # the client went away
    finally:
        fanout.unsubscribe(queue)


async def _send_while_logged_in(
    websocket: WebSocket, queue: asyncio.Queue[str], state: AuthState, claims: TokenClaims
) -> None:
    """Frames until the login ends (server.auth.live), then a close that says why."""
    loop = asyncio.get_running_loop()
    next_check = loop.time() + LOGIN_RECHECK_S
    while True:
        frame: str | None = None
        with contextlib.suppress(TimeoutError):
            frame = await asyncio.wait_for(queue.get(), timeout=max(0.0, next_check - loop.time()))
        ended = ended_here(state, claims)
        if ended is None and loop.time() >= next_check:
            with contextlib.suppress(OperationalError):  # the database is down: telemetry keeps flowing
                ended = await run_in_threadpool(ended_in_database, websocket.app.state.database, claims)
            next_check = loop.time() + LOGIN_RECHECK_S
        if ended is not None:
            await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason=ended)
            return
        if frame is not None:
            await websocket.send_text(frame)
