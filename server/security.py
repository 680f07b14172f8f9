"""The console's web-security layer (issue 12 §5), as ASGI middleware and helpers for `server.app`:

- CSRF: every cookie-authenticated state-changing API request needs the console's own header
  (`X-Requested-With: ssp-rehab`, which no other site can send without a CORS preflight that is refused)
  and, when the browser names one, an allowed `Origin`. Checked before routing, so before any lookup.
  Bearer-token clients are unaffected. The emergency stop only gets the Origin check: the console page
  must always be able to stop motion, logged in or not.
- A cross-origin WebSocket handshake is refused (the telemetry socket authenticates with the cookie).
- Security headers on every response: CSP (with frame-ancestors), X-Frame-Options, nosniff, Referrer-Policy.
- Request bodies over `max_request_body_bytes` get 413 before they are parsed; a JSON string holding a
  lone UTF-16 surrogate gets 422 (it is not text: it can be neither stored nor answered).
- 422 details never echo a password nor more than a short excerpt of the input; logs never hold a token.
- OpenAPI documents the 401, 403 and 413 answers these checks give.
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Callable, Iterable, Mapping
from typing import Any
from urllib.parse import urlsplit

from fastapi import FastAPI
from fastapi.encoders import jsonable_encoder
from starlette.datastructures import Headers, MutableHeaders
from starlette.requests import cookie_parser
from starlette.responses import JSONResponse
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from server.errors import InvalidFieldError
from server.jsonable import to_jsonable

CSRF_HEADER = "X-Requested-With"
CSRF_HEADER_VALUE = "ssp-rehab"
UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
API_PREFIX = "/api/"
# Only the Origin check: the stop must work from the page logged in or not, and a login reads no cookie.
ORIGIN_CHECK_ONLY = frozenset({"/api/v1/estop", "/api/v1/auth/login"})
DOCUMENTATION_PATHS = frozenset({"/docs", "/docs/oauth2-redirect", "/redoc"})
EXCERPT_CHARS = 40
logger = logging.getLogger(__name__)
# A field is secret when a word of its name is one of these: password, new_password, api_key, refresh_token, ...
SECRET_WORDS = frozenset({"password", "passwd", "passphrase", "secret", "token", "key"})


# --- origins ---------------------------------------------------------------------------------------------


def _normalised_origin(origin: str) -> str:
    return origin.strip().rstrip("/").lower()


def served_origin(scope: Scope) -> str | None:
    """The origin the browser reached: the scheme (after any trusted proxy's X-Forwarded-Proto) and Host."""
    host = Headers(scope=scope).get("host")
    if not host:
        return None
    scheme = {"ws": "http", "wss": "https"}.get(scope.get("scheme", "http"), scope.get("scheme", "http"))
    return _normalised_origin(f"{scheme}://{host}")


def request_origin(headers: Headers) -> str | None:
    """The Origin header, else the origin of the Referer; None when the client names neither (not a browser)."""
    origin = headers.get("origin")
    if origin is not None:
        return _normalised_origin(origin)
    referer = headers.get("referer")
    if referer:
        parts = urlsplit(referer)
        return _normalised_origin(f"{parts.scheme}://{parts.netloc}")
    return None


class OriginPolicy:
    def __init__(self, configured: Iterable[str]) -> None:
        self.configured = frozenset(_normalised_origin(origin) for origin in configured)

    def refusal(self, scope: Scope, origin: str | None) -> str | None:
        """None when `origin` may act on this console; else why not."""
        own = served_origin(scope)
        if origin is None or origin == own or origin in self.configured:
            return None
        return (
            f"cross-site request refused: Origin {origin} is neither this console ({own}) "
            "nor in SSP_REHAB_ALLOWED_ORIGINS"
        )


def _has_bearer_token(headers: Headers) -> bool:
    scheme, _, credentials = headers.get("authorization", "").partition(" ")
    return scheme.lower() == "bearer" and bool(credentials.strip())


class CSRFMiddleware:
    def __init__(self, app: ASGIApp, *, policy: OriginPolicy, cookie_name: str) -> None:
        self.app = app
        self.policy = policy
        self.cookie_name = cookie_name

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "websocket":
            refusal = self.policy.refusal(scope, request_origin(Headers(scope=scope)))
            if refusal is not None:  # closing before accepting answers the handshake with 403
                await send({"type": "websocket.close", "code": 1008, "reason": refusal[:120]})
                return
        elif scope["type"] == "http" and scope["method"] in UNSAFE_METHODS and scope["path"].startswith(API_PREFIX):
            refusal = self.refusal(scope)
            if refusal is not None:
                # Logged: a console behind a proxy that rewrites Host shows up here until ALLOWED_ORIGINS is set.
                logger.warning("refused %s %s: %s", scope["method"], scope["path"], refusal)
                await JSONResponse({"detail": refusal}, status_code=403)(scope, receive, send)
                return
        await self.app(scope, receive, send)

    def refusal(self, scope: Scope) -> str | None:
        headers = Headers(scope=scope)
        if _has_bearer_token(headers):
            return None  # a header no other site can make a browser send: not a forged request
        refusal = self.policy.refusal(scope, request_origin(headers))
        if refusal is not None:
            return refusal
        cookie_authenticated = self.cookie_name in cookie_parser(headers.get("cookie", ""))
        if (
            cookie_authenticated
            and scope["path"] not in ORIGIN_CHECK_ONLY
            and headers.get(CSRF_HEADER) != CSRF_HEADER_VALUE
        ):
            return (
                f"cookie-authenticated request refused: send the header {CSRF_HEADER}: {CSRF_HEADER_VALUE} "
                "(the console's pages do), or use a bearer token"
            )
        return None


# --- security headers ------------------------------------------------------------------------------------

COMMON_HEADERS = {
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "SAMEORIGIN",
    "Referrer-Policy": "no-referrer",
    "Cross-Origin-Opener-Policy": "same-origin",
}
_BASE_POLICY = "default-src 'self'; object-src 'none'; base-uri 'self'; form-action 'self'; frame-ancestors 'self'"
# Swagger UI and ReDoc start from an inline script and inject styles; their pages carry no records.
DOCUMENTATION_POLICY = (  # their assets are served locally (server/api_docs.py): nothing from elsewhere
    f"{_BASE_POLICY}; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
    "font-src 'self' data:; img-src 'self' data:; worker-src 'self' blob:; connect-src 'self'"
)


def application_policy(scope: Scope, connect_to: Iterable[str] = ()) -> str:
    """The web app's policy. The live 3D view is framed from the console itself (server/viz/proxy.py, which
    gives viser's page a policy of its own), so 'self' covers it. `connect_to`: other origins the page may
    send to (the robot's emergency-stop listener)."""
    host = Headers(scope=scope).get("host", "")
    extra = "".join(f" {source}" for source in connect_to)
    return (
        f"{_BASE_POLICY}; script-src 'self'; style-src 'self'; img-src 'self' data: blob:; font-src 'self'; "
        f"connect-src 'self' ws://{host} wss://{host}{extra}; frame-src 'self'; worker-src 'self' blob:"
    )


class SecurityHeadersMiddleware:
    def __init__(self, app: ASGIApp, connect_to: Callable[[Scope], Iterable[str]] | None = None) -> None:
        self.app = app
        self.connect_to = connect_to

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if scope["path"] in DOCUMENTATION_PATHS:
            policy = DOCUMENTATION_POLICY
        else:
            policy = application_policy(scope, self.connect_to(scope) if self.connect_to is not None else ())

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in {**COMMON_HEADERS, "Content-Security-Policy": policy}.items():
                    headers.setdefault(name, value)
            await send(message)

        await self.app(scope, receive, send_with_headers)


# --- request bodies --------------------------------------------------------------------------------------

_SURROGATE_ESCAPE = re.compile(rb"\\u[dD][89a-fA-F][0-9a-fA-F]{2}")


def is_text(value: str) -> bool:
    """False for a string holding a lone UTF-16 surrogate (it cannot be encoded, stored nor answered)."""
    try:
        value.encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def printable(value: str) -> str:
    """`value` with any lone surrogate written as its escape, so that it can be sent back."""
    return value if is_text(value) else value.encode("utf-8", "backslashreplace").decode("utf-8")


def lone_surrogate_location(value: Any, location: tuple[Any, ...] = ()) -> tuple[Any, ...] | None:
    """Where in a parsed JSON document a string (or key) holds a lone surrogate; None if nowhere."""
    if isinstance(value, str):
        return None if is_text(value) else location
    if isinstance(value, dict):
        for key, item in value.items():
            if not is_text(key):
                return (*location, printable(key))
            found = lone_surrogate_location(item, (*location, key))
            if found is not None:
                return found
    if isinstance(value, list):
        for index, item in enumerate(value):
            found = lone_surrogate_location(item, (*location, index))
            if found is not None:
                return found
    return None


def _is_json(headers: Headers) -> bool:
    content_type = headers.get("content-type", "").split(";", 1)[0].strip().lower()
    return content_type in ("", "application/json") or content_type.endswith("+json")


class RequestBodyGuard:
    """413 for a body over the limit (by Content-Length, or counted as it streams in), before any parsing;
    422 for JSON with a lone surrogate. The body is then handed on as it came."""

    def __init__(self, app: ASGIApp, *, max_body_bytes: int) -> None:
        self.app = app
        self.max_body_bytes = max_body_bytes

    def _too_large(self) -> JSONResponse:
        return JSONResponse(
            {"detail": f"request body over {self.max_body_bytes} bytes (SSP_REHAB_MAX_REQUEST_BODY_BYTES)"},
            status_code=413,
        )

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        declared = headers.get("content-length", "")
        if declared.isdigit() and int(declared) > self.max_body_bytes:
            await self._too_large()(scope, receive, send)
            return
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                return  # the client left before sending its body
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_body_bytes:
                await self._too_large()(scope, receive, send)
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        if _is_json(headers) and _SURROGATE_ESCAPE.search(body):
            refusal = _surrogate_refusal(body)
            if refusal is not None:
                await refusal(scope, receive, send)
                return
        handed_on = False

        async def replay() -> Message:
            nonlocal handed_on
            if handed_on:
                return await receive()
            handed_on = True
            return {"type": "http.request", "body": body, "more_body": False}

        await self.app(scope, replay, send)


def _surrogate_refusal(body: bytes) -> JSONResponse | None:
    try:
        document = json.loads(body)
    except ValueError:
        return None  # not JSON at all: the route's own parsing answers 422
    location = lone_surrogate_location(document)
    if location is None:
        return None  # escapes of a proper surrogate pair, or of a backslash
    detail = {
        "loc": ["body", *location],
        "msg": "not valid text: a lone UTF-16 surrogate (\\ud800-\\udfff without its pair) is no character",
        "type": "string_unicode",
    }
    return JSONResponse({"detail": [detail]}, status_code=422)


# --- what answers and logs may show -----------------------------------------------------------------------


def excerpt(value: Any, limit: int = EXCERPT_CHARS) -> Any:
    """A short, sendable rendering of echoed input: long text is cut, structures are summarised."""
    if isinstance(value, str):
        text = printable(value)
        return text if len(text) <= limit else f"{text[:limit]}… ({len(value)} characters)"
    if isinstance(value, dict):
        return f"(an object with {len(value)} fields)"
    if isinstance(value, list | tuple):
        return f"(a list of {len(value)} items)"
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)  # JSON has no NaN or infinity, and a refusal must not fail to send
    return value


def _sendable(value: Any) -> Any:
    if isinstance(value, str):
        return printable(value)
    if isinstance(value, dict):
        return {printable(str(key)): _sendable(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_sendable(item) for item in value]
    return excerpt(value) if isinstance(value, float) else value


def is_secret_field(name: Any) -> bool:
    return any(word in SECRET_WORDS for word in re.split(r"[^a-z0-9]+", str(name).lower()))


def _is_secret(location: Iterable[Any]) -> bool:
    return any(is_secret_field(part) for part in location)


def shown_value(field: str, value: Any) -> str:
    """How a refusal names a value: its repr, cut short; never a secret's."""
    return "(not shown)" if _is_secret(field.split(".")) else str(excerpt(repr(value), 2 * EXCERPT_CHARS))


def safe_validation_errors(errors: Iterable[Mapping[str, Any]]) -> list[dict[str, Any]]:
    """FastAPI's 422 details with the input cut to a short excerpt, and a secret's value never shown."""
    safe = []
    for error in errors:
        item = {key: value for key, value in error.items() if key != "input"}
        if "input" in error:
            item["input"] = "(not shown)" if _is_secret(error.get("loc", ())) else excerpt(error["input"])
        safe.append(_sendable(item))
    return safe


def invalid_field_detail(error: InvalidFieldError) -> list[dict[str, Any]]:
    """A domain refusal as the items of a 422's `detail`: the same shape as FastAPI's own, so that clients read
    every refusal the same way (a preview job's refusal too, `server.prescriptions.preview`)."""
    item = {
        "loc": ["body", *error.field.split(".")],
        "msg": f"{error.field} = {shown_value(error.field, error.value)}: {error.limit}",
        "type": "value_error",
        # The parts apart, as pydantic's own errors carry them: clients word them in their units.
        "input": jsonable_encoder(error.value),
        "ctx": {"limit": error.limit, **({"details": to_jsonable(error.details)} if error.details else {})},
    }
    return safe_validation_errors([item])


_SECRET_PATTERNS = (
    (re.compile(r"(?i)([?&](?:access_)?token=)[^&\s\"']+"), r"\1(redacted)"),
    (re.compile(r"(?i)(bearer\s+)[\w.~+/=-]+"), r"\1(redacted)"),
)


def redact_secrets(text: str) -> str:
    for pattern, replacement in _SECRET_PATTERNS:
        text = pattern.sub(replacement, text)
    return text


class RedactSecrets(logging.Filter):
    """Tokens out of log records: the WebSocket's `?token=` (uvicorn logs the handshake's full path) and any
    bearer header that reaches a message."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.msg, str):
            record.msg = redact_secrets(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(redact_secrets(arg) if isinstance(arg, str) else arg for arg in record.args)
        return True


def install_log_redaction(logger_names: Iterable[str] = ("uvicorn.access", "uvicorn.error")) -> None:
    for name in logger_names:
        logger = logging.getLogger(name)
        if not any(isinstance(f, RedactSecrets) for f in logger.filters):
            logger.addFilter(RedactSecrets())


# --- OpenAPI ---------------------------------------------------------------------------------------------

UNAUTHENTICATED = {"description": "Not logged in, or the login ended: log in again"}
FORBIDDEN = {
    "description": "Refused: a cross-site request (Origin not allowed, or a cookie-authenticated change without "
    f"`{CSRF_HEADER}: {CSRF_HEADER_VALUE}`), or the account's role does not allow it"
}
TOO_LARGE = {"description": "Request body over SSP_REHAB_MAX_REQUEST_BODY_BYTES"}


def document_security_responses(app: FastAPI) -> None:
    """Add the 401, 403 and 413 answers of the checks above to every operation they apply to."""
    generate: Callable[[], dict[str, Any]] = app.openapi
    documented: list[dict[str, Any]] = []

    def openapi() -> dict[str, Any]:
        document = generate()
        if not any(d is document for d in documented):
            for operations in document.get("paths", {}).values():
                for method, operation in operations.items():
                    responses = operation.setdefault("responses", {})
                    if operation.get("security"):
                        responses.setdefault("401", UNAUTHENTICATED)
                    if operation.get("security") or method.upper() in UNSAFE_METHODS:
                        responses.setdefault("403", FORBIDDEN)
                    if "requestBody" in operation:
                        responses.setdefault("413", TOO_LARGE)
            documented.append(document)
        return document

    app.openapi = openapi  # type: ignore[method-assign]
