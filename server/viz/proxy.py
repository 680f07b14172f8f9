"""The 3D view behind the console's login. viser listens on loopback only; the console relays its page
and its WebSocket to logged-in users, so nobody watches a patient's session by reaching viser's port.

viser's client derives its WebSocket address from the page address, so the page served at
`/api/v1/viz/view/` opens `ws(s)://<console>/api/v1/viz/view`, which is relayed here. The relay names the
browser to viser (`?viewer=`, from the login that opened the socket), so that viser's panel follows that
browser's own engineering switch (`POST /viz/controls` from the same login) and a camera preset
(`POST /viz/camera`) turns that browser's views, not another browser's.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
from typing import Any
from urllib.parse import urlencode

import httpx
import websockets
from fastapi import APIRouter, Depends, Request, WebSocket, status
from fastapi.responses import Response
from starlette.concurrency import run_in_threadpool
from websockets.asyncio.client import connect as upstream_connect

from server.auth.dependencies import auth_state, claims_for_token, current_user, token_from_request, user_for_claims
from server.auth.security import TokenClaims
from server.db import Database
from server.errors import WorkerUnavailableError
from server.viz.view import VIEWER_PARAM, LiveView

VIEW_PATH = "/viz/view"
# viser's page runs a bundled app from an inline script and web workers; it shows only the scene.
VIEW_PAGE_POLICY = (
    "default-src 'self'; script-src 'self' 'unsafe-inline' 'unsafe-eval' blob:; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data: blob:; font-src 'self' data:; connect-src 'self' ws: wss: data: blob:; "
    "worker-src 'self' blob:; object-src 'none'; base-uri 'self'; frame-ancestors 'self'"
)
MAX_MESSAGE_BYTES = 50 * 1024 * 1024  # viser's own limit

router = APIRouter(tags=["3d view"])
NO_VIEW = "the 3D view is not running (turned off with SSP_REHAB_VIZ_ENABLED=false, or its port was taken)"


def viewer_of(claims: TokenClaims) -> str:
    """The 3D view's name for one browser: its login session (each login on each device is its own; the
    tabs of one browser share it, as they share the engineering switch), hashed so viser never holds it."""
    return hashlib.sha256(b"ssp-rehab 3D viewer " + claims.session_id.encode()).hexdigest()[:32]


def _view_port(app: Any) -> int | None:
    """viser's loopback port: this process's view, else (`serve --workers N`) the configured port, where
    another web process of this console runs the one view; None when the view is turned off."""
    view: LiveView | None = getattr(app.state, "viz", None)
    if view is not None and view.server is not None:
        return view.port
    settings = app.state.settings
    return int(settings.viz_port) if settings.viz_enabled else None


@router.get(VIEW_PATH + "/", include_in_schema=True, dependencies=[Depends(current_user)])
@router.get(VIEW_PATH + "/{path:path}", include_in_schema=False, dependencies=[Depends(current_user)])
async def view_page(request: Request, path: str = "") -> Response:
    """viser's page, relayed from its loopback port to a logged-in user."""
    port = _view_port(request.app)
    if port is None:
        raise WorkerUnavailableError(NO_VIEW)
    try:
        async with httpx.AsyncClient(timeout=10.0) as client:
            upstream = await client.get(
                f"http://127.0.0.1:{port}/{path}", params=request.query_params, headers={"Accept-Encoding": "identity"}
            )
    except httpx.HTTPError as error:
        raise WorkerUnavailableError(NO_VIEW) from error
    return Response(
        upstream.content,
        status_code=upstream.status_code,
        media_type=upstream.headers.get("content-type"),
        headers={"Content-Security-Policy": VIEW_PAGE_POLICY, "Cache-Control": "no-store"},
    )


def _login(database: Database, websocket: WebSocket) -> tuple[str | None, TokenClaims | None]:
    """(None, the login) when the socket belongs to a logged-in, active user; else (why not, None)."""
    state = auth_state(websocket)
    claims = claims_for_token(token_from_request(websocket, state.cookie_name), state)
    if claims is None:
        return "not authenticated", None
    with database.session() as session:
        return (None, claims) if user_for_claims(session, claims) is not None else ("login session ended", None)


@router.websocket(VIEW_PATH)
async def view_socket(websocket: WebSocket) -> None:
    """viser's WebSocket, relayed both ways once the user is known to be logged in."""
    refusal, claims = await run_in_threadpool(_login, websocket.app.state.database, websocket)
    port = _view_port(websocket.app)
    if refusal is None and port is None:
        refusal = NO_VIEW
    if refusal is not None or port is None or claims is None:
        await websocket.close(code=status.WS_1008_POLICY_VIOLATION, reason=refusal)
        return
    offered = [p for p in websocket.scope.get("subprotocols", []) if p.startswith("viser-v")]
    try:
        upstream = await upstream_connect(
            f"ws://127.0.0.1:{port}/?{urlencode({VIEWER_PARAM: viewer_of(claims)})}",
            subprotocols=offered,  # viser checks its client's version in the subprotocol
            max_size=MAX_MESSAGE_BYTES,
            compression=None,
        )
    except (OSError, websockets.exceptions.WebSocketException):
        await websocket.close(code=status.WS_1013_TRY_AGAIN_LATER, reason=NO_VIEW)
        return
    await websocket.accept(subprotocol=upstream.subprotocol)
    async with upstream:
        await _relay(websocket, upstream)


async def _relay(browser: WebSocket, upstream: Any) -> None:
    async def to_browser() -> None:
        async for message in upstream:
            if isinstance(message, bytes):
                await browser.send_bytes(message)
            else:
                await browser.send_text(message)

    async def to_viser() -> None:
        while True:
            message = await browser.receive()
            if message["type"] == "websocket.disconnect":
                return
            if message.get("bytes") is not None:
                await upstream.send(message["bytes"])
            elif message.get("text") is not None:
                await upstream.send(message["text"])

    tasks = [asyncio.ensure_future(to_browser()), asyncio.ensure_future(to_viser())]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        for task in tasks:
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await task
        with contextlib.suppress(Exception):
            await browser.close()
