"""The console service's FastAPI application factory: `create_app(settings)`.

REST under `/api/v1`, the telemetry WebSocket, OpenAPI at `/docs`, and the clinician web app
(`frontend_static/`) at `/`. On start it upgrades the database (Alembic), attaches to its robot's daemon
(starting it when none runs, server.robotd) and fans telemetry out to WebSocket clients. See docs/service.md.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import hmac
import importlib.metadata
import logging
import os
from collections.abc import AsyncIterator
from typing import Any
from urllib.parse import urlsplit
from zoneinfo import ZoneInfo

from fastapi import APIRouter, FastAPI, Request, status
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from sqlalchemy.exc import IntegrityError, InternalError, OperationalError
from sqlalchemy.orm.exc import StaleDataError
from starlette.datastructures import Headers
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

from core.robot import default_twin, load_twin
from server.api_docs import install_offline_docs
from server.auth.dependencies import AuthState
from server.auth.safe_commands import LoginCache
from server.auth.security import TokenSigner
from server.auth.throttle import LoginThrottle
from server.concurrency import etag
from server.db import Database, create_database_engine, load_models, refused_write_reason, upgrade_database
from server.errors import (
    ConflictError,
    InvalidFieldError,
    NotFoundError,
    PreconditionRequiredError,
    StaleVersionError,
    WorkerUnavailableError,
)
from server.exports.jobs import KEEP_FINISHED_S, ExportJobs
from server.file_modes import private_directory
from server.observability.health import DatabaseProbe
from server.prescriptions.preview import PreviewProcess
from server.prescriptions.preview_jobs import PREVIEW_JOBS_DIRECTORY, PreviewJobStore
from server.realtime.supervisor import SupervisorConfig
from server.robotd.daemon import RobotDaemon
from server.robotd.estop_listener import page_stop_url
from server.robotd.interfaces import RobotLink
from server.robotd.link import DaemonLink, LocalLink, attach_robot
from server.robotd.plan_store import PlanStore
from server.robotd.planner import InlinePlanner
from server.robotd.recovery import recover_open_runs
from server.robotd.status import RobotPaths, daemon_running
from server.security import (
    CSRF_HEADER,
    CSRFMiddleware,
    OriginPolicy,
    RequestBodyGuard,
    SecurityHeadersMiddleware,
    document_security_responses,
    install_log_redaction,
    invalid_field_detail,
    safe_validation_errors,
)
from server.sessions.fanout import TelemetryFanout
from server.settings import Settings
from server.viz.view import start_view

logger = logging.getLogger(__name__)

API_PREFIX = "/api/v1"
START_WORKER = object()  # `create_app(worker=...)` default: attach to the robot daemon if settings allow it
DATABASE_UNAVAILABLE = "the database is unavailable"
DATABASE_READ_ONLY = "the database is read-only"


class RedactQueryStrings(logging.Filter):
    """Drop query strings from uvicorn's access log: searches carry patient names and record numbers."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple) and len(record.args) >= 3:
            args = list(record.args)
            if isinstance(args[2], str):
                args[2] = args[2].split("?", 1)[0]
                record.args = tuple(args)
        return True


def _install_access_log_redaction() -> None:
    access_logger = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, RedactQueryStrings) for f in access_logger.filters):
        access_logger.addFilter(RedactQueryStrings())


def stale_version_response(error: StaleVersionError, zone: ZoneInfo) -> JSONResponse:
    """412 naming the current version, who changed it and when (clinic time): what the console shows."""
    who = f" by {error.changed_by}" if error.changed_by else ""
    when = (
        f" at {error.changed_at.astimezone(zone):%H:%M} ({error.changed_at.astimezone(zone):%Y-%m-%d})"
        if (error.changed_at is not None)
        else ""
    )
    detail = (
        f"{error.resource} {error.resource_id} was changed{who}{when}: it is now version {error.current}, your "
        f"change was based on version {error.expected}. Nothing was written: reload it and make your change again."
    )
    body = {
        "detail": detail,
        "current_version": error.current,
        "changed_by": error.changed_by,
        "changed_at": error.changed_at.isoformat() if error.changed_at is not None else None,
    }
    headers = {"ETag": etag(error.current)} if error.current is not None else None
    return JSONResponse(body, status_code=status.HTTP_412_PRECONDITION_FAILED, headers=headers)


def _error_handlers(app: FastAPI) -> None:
    @app.exception_handler(RequestValidationError)
    async def unprocessable(_request: Request, error: RequestValidationError) -> JSONResponse:
        detail = jsonable_encoder(safe_validation_errors(error.errors()))
        return JSONResponse({"detail": detail}, status_code=status.HTTP_422_UNPROCESSABLE_CONTENT)

    @app.exception_handler(NotFoundError)
    async def not_found(_request: Request, error: NotFoundError) -> JSONResponse:
        return JSONResponse({"detail": str(error)}, status_code=status.HTTP_404_NOT_FOUND)

    @app.exception_handler(ConflictError)
    async def conflict(_request: Request, error: ConflictError) -> JSONResponse:
        return JSONResponse({"detail": str(error), "field": error.field}, status_code=status.HTTP_409_CONFLICT)

    @app.exception_handler(InvalidFieldError)
    async def invalid(_request: Request, error: InvalidFieldError) -> JSONResponse:
        return JSONResponse({"detail": invalid_field_detail(error)}, status_code=status.HTTP_422_UNPROCESSABLE_CONTENT)

    @app.exception_handler(PreconditionRequiredError)
    async def precondition_required(_request: Request, error: PreconditionRequiredError) -> JSONResponse:
        return JSONResponse({"detail": str(error)}, status_code=status.HTTP_428_PRECONDITION_REQUIRED)

    @app.exception_handler(StaleVersionError)
    async def stale_version(_request: Request, error: StaleVersionError) -> JSONResponse:
        return stale_version_response(error, app.state.settings.clinic_zone())

    @app.exception_handler(StaleDataError)
    async def stale_data(_request: Request, _error: StaleDataError) -> JSONResponse:
        # Two changes based on one version raced past the check; the database let only the first through.
        return JSONResponse(
            {"detail": "the record was changed by someone else at the same moment: nothing was written; reload it "
             "and make your change again", "current_version": None},
            status_code=status.HTTP_412_PRECONDITION_FAILED,
        )  # fmt: skip

    @app.exception_handler(WorkerUnavailableError)
    async def no_worker(_request: Request, error: WorkerUnavailableError) -> JSONResponse:
        return JSONResponse({"detail": str(error)}, status_code=status.HTTP_503_SERVICE_UNAVAILABLE)

    @app.exception_handler(OperationalError)
    @app.exception_handler(InternalError)
    async def database_refused(request: Request, error: OperationalError | InternalError) -> JSONResponse:
        # The database itself failed (read-only, full, locked, unreachable): not the request's fault. The
        # browser learns what happened, never where (host, port, file): that goes to the service's log.
        database: Database | None = app.state.database
        reason = refused_write_reason(error, database.engine if database is not None else None)
        if reason is None and isinstance(error, InternalError):
            raise error
        logger.error("%s %s: %s", request.method, request.url.path, reason or str(error.orig).splitlines()[0][:500])
        detail = DATABASE_READ_ONLY if reason is not None else DATABASE_UNAVAILABLE
        if reason is not None:
            app.state.database_refusal = detail  # /health says so until a restart finds it writable again
        return JSONResponse({"detail": f"{detail}: nothing was written"}, status_code=503)

    @app.exception_handler(IntegrityError)
    async def integrity(_request: Request, _error: IntegrityError) -> JSONResponse:
        # A concurrent change won the race (unique key, foreign key); the transaction was rolled back.
        return JSONResponse(
            {"detail": "conflicting concurrent change: nothing was written, try again"},
            status_code=status.HTTP_409_CONFLICT,
        )


def _announce_first_start(database: Database, settings: Settings) -> None:
    from server.users.first_admin import first_admin_command
    from server.users.service import count_users

    with database.session() as session:
        if count_users(session=session) == 0:
            logger.warning(
                "no accounts yet: create the first admin with this command (it asks for the password):\n    %s",
                first_admin_command(settings.data_dir.resolve()),
            )


def _api_router() -> APIRouter:
    from server.audit.routes import router as audit_router
    from server.auth.routes import public_router as auth_public_router
    from server.auth.routes import router as auth_router
    from server.patients.routes import router as patients_router
    from server.prescriptions.preview import router as prescription_preview_router
    from server.prescriptions.routes import router as prescriptions_router
    from server.reports.routes import router as reports_router
    from server.reviews.routes import router as reviews_router
    from server.scheduling.routes import public_router as scheduling_public_router
    from server.scheduling.routes import router as scheduling_router
    from server.sessions.balance import router as balance_router
    from server.sessions.routes import estop_router, export_router, motion_router, websocket_router
    from server.sessions.routes import router as sessions_router
    from server.users.routes import router as users_router
    from server.viz.proxy import router as viz_proxy_router
    from server.viz.routes import router as viz_router

    api = APIRouter(prefix=API_PREFIX)

    @api.get("/health", tags=["health"])
    def health(request: Request) -> dict[str, Any]:
        """Public liveness check: the service is up, and its robot daemon's state (starting, ready, fault
        or absent) with the reason; read from shared memory, so it never waits for the robot. `degraded`,
        with every reason in `reasons`, when something the console needs does not work."""
        robot: RobotLink | None = request.app.state.robot
        if robot is None:
            daemon = {"state": "absent", "reason": "this console runs without a robot"}
        else:
            daemon = robot.status().to_dict()
        reasons: list[str] = []
        # Reachable: a cached, bounded SELECT 1. Read-only: known from the write it refused (probing writes
        # here would take SQLite's write lock on every health check).
        unreachable = request.app.state.database_probe.unreachable_reason(request.app.state.database)
        refusal: str | None = unreachable or getattr(request.app.state, "database_refusal", None)
        if refusal is not None:
            reasons.append(refusal)
        # The robot daemon's recorder cannot write (disk full, I/O error): runs stop, starts are refused.
        recording_failure: str | None = daemon.get("recording_failure")
        if recording_failure is not None:
            reasons.append(f"the robot cannot record: {recording_failure}")
        return {
            "status": "degraded" if reasons else "ok",
            "reasons": reasons,
            "recording": {"ok": recording_failure is None, "reason": recording_failure},
            "robot_connected": daemon["state"] == "ready",
            "robot": daemon,
            "database": {"reachable": unreachable is None, "writable": refusal is None, "reason": refusal},
            # The worker's scheduling: SCHED_FIFO and a CPU of its own granted, or what to configure (issue 20).
            "realtime": getattr(robot, "realtime", None),
            "web_pid": os.getpid(),  # which of the console's web processes (`serve --workers N`) answered
            "clinic_timezone": request.app.state.settings.timezone,  # the console shows every time in it
            # Where the page sends its emergency stop (the robot's stop listener); /api/v1/estop if it fails.
            "estop": {
                "url": stop_listener_url(request.app, request.headers.get("host"), request.url.scheme),
                "fallback": f"{API_PREFIX}/estop",
            },
        }

    for router in (
        auth_public_router,
        auth_router,
        users_router,
        patients_router,
        balance_router,
        prescription_preview_router,
        prescriptions_router,
        scheduling_router,
        scheduling_public_router,
        sessions_router,
        reviews_router,
        reports_router,
        motion_router,
        estop_router,
        export_router,
        audit_router,
        viz_router,
        viz_proxy_router,
        websocket_router,
    ):
        api.include_router(router)
    return api


def create_app(
    settings: Settings | None = None, *, database: Database | None = None, worker: Any = START_WORKER
) -> FastAPI:
    """The service. `database` and `worker` are injected by tests; by default the database comes from the
    settings (and is upgraded to the latest schema) and the real-time worker is started if installed."""
    settings = settings or Settings()
    load_models()
    twin = load_twin(settings.robot_file) if settings.robot_file else default_twin()
    private_directory(settings.data_dir)  # patient data, password hashes, the token key: owner-only
    secret_key = settings.resolved_secret_key()

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        owned_engine = None
        app.state.database = database
        if database is None:
            owned_engine = create_database_engine(settings.resolved_database_url())
            await asyncio.to_thread(upgrade_database, owned_engine)
            app.state.database = Database(owned_engine)
        await asyncio.to_thread(_announce_first_start, app.state.database, settings)
        started_here = worker is START_WORKER
        robot: RobotLink | None = None
        if started_here and settings.start_worker:
            robot = await asyncio.to_thread(_attach_robot, settings, app.state.database)
        elif not started_here and worker is not None:  # an in-memory worker (tests): the daemon runs in here
            robot = LocalLink(
                RobotDaemon(
                    robot=settings.robot,
                    worker=worker,
                    database=app.state.database,
                    journal_dir=None,
                    planner=InlinePlanner(twin, settings.control_rate_hz, SupervisorConfig()),
                    twin=twin,
                    plan_store=PlanStore(settings.data_dir.resolve() / "plans", settings.plan_store_max_mb * 1_000_000),
                    chunk_period_s=settings.log_flush_interval_s,
                    shutdown_wait_s=0.0,  # an in-memory worker has no stop to wait for
                )
            )
            robot.open()
        app.state.robot = robot
        app.state.viz = await asyncio.to_thread(start_view, settings, twin, robot) if started_here else None
        fanout_task = None
        if robot is not None:
            app.state.fanout = TelemetryFanout(robot, settings.telemetry_rate_hz)
            fanout_task = asyncio.create_task(app.state.fanout.run_forever())
        try:
            yield
        finally:
            if app.state.viz is not None:
                await asyncio.to_thread(app.state.viz.stop)
            if fanout_task is not None:
                fanout_task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await fanout_task
            if robot is not None:
                await asyncio.to_thread(robot.close)  # a daemon: `serve` decides on its exit; an in-process one stops
            await asyncio.to_thread(app.state.export_jobs.close)
            app.state.preview_process.close()
            if owned_engine is not None:
                owned_engine.dispose()

    app = FastAPI(
        title="ssp-rehab console",
        version=_version(),
        description="Therapist console of the twin 6-SSP balance-rehabilitation robot. Log in with "
        "`POST /api/v1/auth/login`, then send the `access_token` as a bearer token (or use the session cookie).",
        lifespan=lifespan,
        docs_url=None,  # served from local assets below (server.api_docs)
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.twin = twin
    app.state.preview_process = PreviewProcess()  # previews never run in a web process (issue 20)
    app.state.pseudonym_key = hmac.new(secret_key, b"patient pseudonyms", hashlib.sha256).digest()
    app.state.auth = AuthState(
        signer=TokenSigner(secret_key),
        throttle=LoginThrottle(
            settings.login_max_failures, settings.login_window_s, delay_max_s=settings.login_delay_max_s
        ),
        cookie_name=settings.cookie_name,
    )
    app.state.database = database
    app.state.database_probe = DatabaseProbe()
    app.state.login_cache = LoginCache()
    app.state.robot = None
    app.state.fanout = None
    app.state.viz = None
    app.state.export_jobs = ExportJobs(settings.data_dir / "export-jobs")
    # On disk, so that any web process answers a job's poll; kept as long as a finished export.
    app.state.preview_jobs = PreviewJobStore(settings.data_dir / PREVIEW_JOBS_DIRECTORY, keep_s=KEEP_FINISHED_S)
    _security_middleware(app, settings)
    _error_handlers(app)
    _install_audit_journal(app, settings)
    _install_observability(app, settings)
    document_security_responses(app)
    app.include_router(_api_router())
    frontend = settings.resolved_frontend_dir()
    if frontend is not None:
        install_offline_docs(app)
        app.mount("/", StaticFiles(directory=frontend, html=True), name="frontend")
    _install_access_log_redaction()
    install_log_redaction()
    return app


def app_from_environment() -> FastAPI:
    """The app factory each web process of `ssp-rehab serve --workers N` calls (uvicorn needs an import
    string to start several processes): the settings come from the environment, where `serve` has put
    its command-line options as SSP_REHAB_* variables. Each process is a fresh interpreter, so it
    configures its own (structured) logging, as `serve` does for one process."""
    from server.observability.logs import configure_logging

    settings = Settings()
    configure_logging(settings.log_format)
    return create_app(settings)


def _security_middleware(app: FastAPI, settings: Settings) -> None:
    """A request meets the security headers, the proxy headers (when proxies are configured), the CSRF check,
    the body limit, then CORS (`add_middleware` adds outside what is there, so innermost first)."""
    if settings.cors_origins:
        app.add_middleware(
            CORSMiddleware,
            allow_origins=settings.cors_origins,
            allow_credentials=True,
            allow_methods=["GET", "POST", "PUT", "PATCH", "DELETE"],
            allow_headers=["Authorization", "Content-Type", CSRF_HEADER],
        )
    app.add_middleware(RequestBodyGuard, max_body_bytes=settings.max_request_body_bytes)
    app.add_middleware(
        CSRFMiddleware,
        policy=OriginPolicy([*settings.allowed_origins, *settings.cors_origins]),
        cookie_name=settings.cookie_name,
    )
    if settings.trusted_proxies:
        app.add_middleware(ProxyHeadersMiddleware, trusted_hosts=settings.trusted_proxies)
    # Outside Starlette's outermost error middleware, so that even a crash's bare 500 carries the headers.
    build_stack = app.build_middleware_stack
    app.build_middleware_stack = lambda: SecurityHeadersMiddleware(  # type: ignore[method-assign]
        build_stack(), connect_to=lambda scope: _stop_listener_origins(app, scope)
    )


def stop_listener_url(app: FastAPI, host: str | None, scheme: str) -> str | None:
    """The robot's emergency-stop listener as the page reaches it (None: no robot, or no listener yet)."""
    if app.state.robot is None or not isinstance(app.state.robot, DaemonLink):
        return None
    settings: Settings = app.state.settings
    return page_stop_url(settings, RobotPaths(settings.data_dir.resolve(), settings.robot), host, scheme)


def _stop_listener_origins(app: FastAPI, scope: Any) -> list[str]:
    if scope["path"] != "/" and not scope["path"].endswith(".html"):
        return []  # only pages run scripts
    url = stop_listener_url(app, Headers(scope=scope).get("host"), scope.get("scheme", "http"))
    parts = urlsplit(url or "")
    return [f"{parts.scheme}://{parts.netloc}"] if parts.scheme and parts.netloc else []


def _install_observability(app: FastAPI, settings: Settings) -> None:
    """GET /metrics (Prometheus), request ids and latency by route, the robot worker's metrics tap."""
    from server.observability.service import install_observability

    install_observability(app, settings)


def _install_audit_journal(app: FastAPI, settings: Settings) -> None:
    """Audited reads go through a write-ahead journal in the data directory (server.audit.journal): opened,
    and what a crashed process left replayed, once the database is up; drained when the service stops."""
    from server.audit.journal import AuditJournal
    from server.audit.service import use_journal

    journal = AuditJournal(settings.data_dir / "audit-journal", drain_interval_s=settings.audit_drain_interval_s)
    app.state.audit_journal = journal
    inner_lifespan = app.router.lifespan_context

    @contextlib.asynccontextmanager
    async def lifespan_with_journal(app: FastAPI) -> AsyncIterator[Any]:
        async with inner_lifespan(app) as state:
            database: Database = app.state.database
            await asyncio.to_thread(journal.open, database)
            use_journal(database.engine, journal)
            try:
                yield state
            finally:
                use_journal(database.engine, None)
                await asyncio.to_thread(journal.close)

    app.router.lifespan_context = lifespan_with_journal


def _attach_robot(settings: Settings, database: Database) -> RobotLink:
    """Runs a crash left open are closed first when no daemon runs (it would close them itself)."""
    paths = RobotPaths(settings.data_dir.resolve(), settings.robot)
    if not daemon_running(paths):
        closed = recover_open_runs(database=database, robot=settings.robot, journal_dir=paths.journal)
        if closed:
            logger.warning("closed runs left open by a crash as interrupted: %s", closed)
    return attach_robot(settings)


def _version() -> str:
    try:
        return importlib.metadata.version("ssp-rehab")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"
