"""Request authentication and role checks, as FastAPI dependencies.

`authenticated_claims` checks only the token's signature, expiry and this process's revocation list: no
database. The emergency stop uses it alone. `current_user` adds the login-session and account checks
that every other protected route relies on.
"""

from __future__ import annotations

import datetime as dt
import threading
from dataclasses import dataclass, field
from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy import select
from starlette.requests import HTTPConnection

from server.auth.models import AuthSession
from server.auth.security import TokenClaims, TokenSigner
from server.auth.throttle import LoginThrottle
from server.db import Database, SessionDep, utc_now
from server.users.models import User

# Declared for OpenAPI (the "Authorize" button); the checks below read the request themselves.
bearer_scheme = HTTPBearer(auto_error=False, description="The `access_token` from POST /api/v1/auth/login.")


@dataclass
class AuthState:
    signer: TokenSigner
    throttle: LoginThrottle
    cookie_name: str
    revoked_session_ids: set[str] = field(default_factory=set)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def revoke(self, session_id: str) -> None:
        with self.lock:
            self.revoked_session_ids.add(session_id)

    def is_revoked(self, session_id: str) -> bool:
        with self.lock:
            return session_id in self.revoked_session_ids


def unauthorized(detail: str = "not authenticated: log in first") -> HTTPException:
    return HTTPException(status.HTTP_401_UNAUTHORIZED, detail=detail, headers={"WWW-Authenticate": "Bearer"})


def auth_state(request: HTTPConnection) -> AuthState:
    state: AuthState = request.app.state.auth
    return state


def token_from_request(request: HTTPConnection, cookie_name: str) -> str | None:
    header = request.headers.get("authorization", "")
    scheme, _, credentials = header.partition(" ")
    if scheme.lower() == "bearer" and credentials.strip():
        return credentials.strip()
    return request.cookies.get(cookie_name) or None


def claims_for_token(token: str | None, state: AuthState) -> TokenClaims | None:
    if not token:
        return None
    claims = state.signer.verify(token)
    if claims is None or state.is_revoked(claims.session_id):
        return None
    return claims


async def authenticated_claims(
    request: Request, _bearer: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)] = None
) -> TokenClaims:
    state = auth_state(request)
    claims = claims_for_token(token_from_request(request, state.cookie_name), state)
    if claims is None:
        raise unauthorized()
    return claims


def user_for_claims(session: SessionDep, claims: TokenClaims) -> User | None:
    # One query for the login session and the account: this runs on every authenticated request.
    return session.scalar(
        select(User)
        .join(AuthSession, AuthSession.user_id == User.id)
        .where(
            AuthSession.id == claims.session_id,
            AuthSession.revoked_at.is_(None),
            AuthSession.expires_at > utc_now(),
            User.id == claims.user_id,
            User.is_active.is_(True),
        )
    )


def credential_of(database: Database, claims: TokenClaims | None, token_given: bool) -> tuple[int | None, str]:
    """(user id, what a request proved), for the emergency stop's audit: a user only for a valid, unrevoked
    login of an active account (`claims`: the token's, already checked for signature and expiry)."""
    if not token_given:
        return None, "none"
    if claims is None:
        return None, "invalid, expired or revoked token"
    with database.session() as session:
        user = user_for_claims(session, claims)
        return (user.id, "login session") if user is not None else (None, "ended login session or inactive account")


def current_user(session: SessionDep, claims: Annotated[TokenClaims, Depends(authenticated_claims)]) -> User:
    user = user_for_claims(session, claims)
    if user is None:
        raise unauthorized("login session ended: log in again")
    return user


CurrentUser = Annotated[User, Depends(current_user)]


def require_admin(user: CurrentUser) -> User:
    if user.role != "admin":
        raise HTTPException(status.HTTP_403_FORBIDDEN, detail=f"role = {user.role!r}: this needs the admin role")
    return user


AdminUser = Annotated[User, Depends(require_admin)]


def expires_at(claims: TokenClaims) -> dt.datetime:
    return dt.datetime.fromtimestamp(claims.expires_at_epoch_s, dt.UTC)
