"""Connections that outlive a request (the telemetry WebSocket) end with their login: logout in this
process at once, and every `LOGIN_RECHECK_S` the database's word on revocation (by another web process),
deactivation and expiry (issue 20, defect 16)."""

from __future__ import annotations

import time

from sqlalchemy import select

from server.auth.dependencies import AuthState
from server.auth.models import AuthSession
from server.auth.security import TokenClaims
from server.db import Database, utc_now
from server.users.models import User

LOGIN_RECHECK_S = 1.0


def ended_here(state: AuthState, claims: TokenClaims) -> str | None:
    """Why the login ended, as far as this process knows without the database (cheap: every frame)."""
    if state.is_revoked(claims.session_id):
        return "logged out"
    if claims.expires_at_epoch_s <= time.time():
        return "login session expired"
    return None


def ended_in_database(database: Database, claims: TokenClaims) -> str | None:
    """Why the login ended according to the database, or None while it holds."""
    with database.session() as session:
        row = session.execute(
            select(User.is_active, AuthSession.revoked_at, (AuthSession.expires_at > utc_now()).label("current"))
            .join(User, User.id == AuthSession.user_id)
            .where(AuthSession.id == claims.session_id, User.id == claims.user_id)
        ).one_or_none()
    if row is None:
        return "login session ended"
    if not row.is_active:
        return "account deactivated"
    if row.revoked_at is not None:
        return "login session revoked"
    if not row.current:
        return "login session expired"
    return None
