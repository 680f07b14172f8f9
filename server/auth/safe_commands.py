"""The login check of the commands that only make the robot safer (stop, pause) and of the robot's state:
it never waits for the database (issue 20, defect 6; decision in docs/service.md, "Stopping never needs
the database").

The signed token is verified without the database (signature, expiry, this process's revocations). The
login session and account (revoked in another web process, account deactivated) are then checked in the
database with a short bound, and a confirmed login is cached for `LOGIN_CACHE_S`. A login the database
says has ended is refused (401). When the database does not answer in time, the command goes ahead on the
signed token alone, because stopping is always safe (the emergency stop needs no login at all), and the
credential recorded with the command says so.
"""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.exc import SQLAlchemyError

from server.auth.dependencies import authenticated_claims, unauthorized, user_for_claims
from server.auth.security import TokenClaims
from server.db import Database

LOGIN_CHECK_TIMEOUT_S = 0.5  # the longest a stop waits for the database's view of the login
LOGIN_CACHE_S = 30.0  # a login the database confirmed is not asked again for this long
VERIFIED = "login session"
TOKEN_ONLY = "signed token; login session not checked: the database is unavailable"

# Its own small pool: a hung database holds these threads, never the request threads.
_checks = ThreadPoolExecutor(max_workers=2, thread_name_prefix="safe-command-login")


@dataclass(frozen=True)
class SafeCommandLogin:
    user_id: int
    credential: str  # what the request proved: VERIFIED or TOKEN_ONLY, recorded with the command


class LoginCache:
    """Logins the database confirmed recently, by login-session id."""

    def __init__(self) -> None:
        self._confirmed: dict[str, tuple[int, float]] = {}
        self._lock = threading.Lock()

    def get(self, claims: TokenClaims) -> int | None:
        with self._lock:
            entry = self._confirmed.get(claims.session_id)
        if entry is None or time.monotonic() - entry[1] > LOGIN_CACHE_S or entry[0] != claims.user_id:
            return None
        return entry[0]

    def put(self, claims: TokenClaims) -> None:
        with self._lock:
            self._confirmed[claims.session_id] = (claims.user_id, time.monotonic())

    def forget(self, claims: TokenClaims) -> None:
        with self._lock:
            self._confirmed.pop(claims.session_id, None)


def _login_in_database(database: Database, claims: TokenClaims) -> bool:
    with database.session() as session:
        return user_for_claims(session, claims) is not None


def safe_command_login(
    request: Request, claims: Annotated[TokenClaims, Depends(authenticated_claims)]
) -> SafeCommandLogin:
    cache: LoginCache = request.app.state.login_cache
    if cache.get(claims) is not None:
        return SafeCommandLogin(claims.user_id, VERIFIED)
    check = _checks.submit(_login_in_database, request.app.state.database, claims)
    try:
        active = check.result(LOGIN_CHECK_TIMEOUT_S)
    except (FutureTimeout, SQLAlchemyError, OSError):  # unreachable, locked, slow: the command goes ahead
        return SafeCommandLogin(claims.user_id, TOKEN_ONLY)
    if not active:
        cache.forget(claims)
        raise unauthorized("login session ended: log in again")
    cache.put(claims)
    return SafeCommandLogin(claims.user_id, VERIFIED)


SafeCommandUser = Annotated[SafeCommandLogin, Depends(safe_command_login)]
