"""Wiring observability into the app: the request middleware (latency histogram, request id, run id,
one structured log line per request), and `GET /metrics`: this process's metrics, then the robot
daemon's (server.observability.metrics)."""

from __future__ import annotations

import hmac
import logging
import time
import uuid
from typing import Any

import structlog
from fastapi import FastAPI, Request, Response, status
from fastapi.routing import iter_route_contexts
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.observability.metrics import ServiceMetrics
from server.robotd.interfaces import RobotLink
from server.robotd.status import DaemonState
from server.settings import Settings

# A stdlib logger: with the service's logging set up (server.observability.logs) its lines are JSON with the
# request and run ids; where nobody set up logging (tests, `uvicorn --factory`) INFO costs one level check.
logger = logging.getLogger("server.requests")
REQUEST_ID_HEADER = b"x-request-id"


class RequestObservation:
    """Pure ASGI middleware (cheaper than BaseHTTPMiddleware): times each HTTP request under its route
    template, binds `request_id` (the client's X-Request-ID or a new one) and `run_id` to the logs of the
    request, returns the request id, and logs one line without the query string (it can hold names)."""

    def __init__(self, app: ASGIApp, metrics: ServiceMetrics, fastapi_app: FastAPI) -> None:
        self.app = app
        self.metrics = metrics
        self.fastapi_app = fastapi_app
        self._templates: dict[Any, str] | None = None

    def _template(self, scope: Scope) -> str:
        """The matched route's full path template (with the prefixes of the routers it was included in)."""
        if self._templates is None:  # the routes are fixed once the app serves
            self._templates = {
                context.endpoint: context.path
                for context in iter_route_contexts(self.fastapi_app.routes)
                if context.path is not None
            }
        endpoint = scope.get("endpoint")
        return self._templates.get(endpoint) or getattr(scope.get("route"), "path", None) or "unmatched"

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        given = dict(scope["headers"]).get(REQUEST_ID_HEADER, b"").decode("latin-1")[:64]
        request_id = given if given.replace("-", "").isalnum() else uuid.uuid4().hex
        run_id = _active_run_id(self.fastapi_app)
        structlog.contextvars.bind_contextvars(request_id=request_id, run_id=run_id)
        started = time.perf_counter()
        status_code = 500

        async def send_with_id(message: Message) -> None:
            nonlocal status_code
            if message["type"] == "http.response.start":
                status_code = message["status"]
                message["headers"] = [*message.get("headers", []), (REQUEST_ID_HEADER, request_id.encode())]
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            elapsed = time.perf_counter() - started
            template = self._template(scope)
            self.metrics.request_seconds.labels(scope["method"], template, str(status_code)).observe(elapsed)
            if template != "/metrics" and logger.isEnabledFor(logging.INFO):
                logger.info(
                    "request",
                    extra={
                        "method": scope["method"],
                        "route": template,
                        "status": status_code,
                        "duration_ms": round(elapsed * 1e3, 2),
                    },
                )
            structlog.contextvars.unbind_contextvars("request_id", "run_id")


def _active_run_id(app: FastAPI) -> int | None:
    """The run the robot daemon records, from its status in shared memory (no request to the daemon)."""
    robot: RobotLink | None = getattr(app.state, "robot", None)
    return robot.status().active_run_id if robot is not None else None


def _robot_metrics_text(app: FastAPI, metrics: ServiceMetrics) -> str:
    """The daemon's robot metrics; empty (and robot_connected 0) while no daemon answers."""
    robot: RobotLink | None = getattr(app.state, "robot", None)
    robot_status = robot.status() if robot is not None else None
    metrics.robot_connected.set(1.0 if robot_status is not None and robot_status.ready else 0.0)
    metrics.active_run.set(1.0 if robot_status is not None and robot_status.active_run_id is not None else 0.0)
    if robot is None or robot_status is None or robot_status.state is DaemonState.ABSENT:
        return ""
    try:
        return robot.metrics_text()
    except Exception as error:  # a daemon busy or going away: this process's metrics still answer
        logger.warning("the robot daemon's metrics are unavailable: %s", error)
        return ""


def _metrics_route(app: FastAPI, settings: Settings, metrics: ServiceMetrics) -> None:
    token = settings.metrics_token.get_secret_value().encode() if settings.metrics_token is not None else None

    @app.get("/metrics", tags=["observability"], include_in_schema=True, response_class=Response)
    def prometheus_metrics(request: Request) -> Response:
        """Prometheus text format. Closed unless SSP_REHAB_METRICS_TOKEN is set; then it needs
        `Authorization: Bearer <that token>` (401 without credentials, 403 with wrong ones)."""
        if token is None:
            return Response("metrics are closed: set SSP_REHAB_METRICS_TOKEN to open them\n", status.HTTP_403_FORBIDDEN)
        scheme, _, given = request.headers.get("authorization", "").partition(" ")
        if scheme.lower() != "bearer" or not given:
            return Response(
                "metrics need Authorization: Bearer <SSP_REHAB_METRICS_TOKEN>\n",
                status.HTTP_401_UNAUTHORIZED,
                headers={"WWW-Authenticate": "Bearer"},
            )
        if not hmac.compare_digest(given.strip().encode(), token):
            return Response("wrong metrics token\n", status.HTTP_403_FORBIDDEN)
        robot_text = _robot_metrics_text(app, metrics)
        return Response(generate_latest(metrics.registry) + robot_text.encode(), media_type=CONTENT_TYPE_LATEST)


def install_observability(app: FastAPI, settings: Settings) -> None:
    """Metrics and request ids for this web process, and `GET /metrics`."""
    metrics = ServiceMetrics()
    app.state.metrics = metrics
    app.add_middleware(RequestObservation, metrics=metrics, fastapi_app=app)
    _metrics_route(app, settings, metrics)
