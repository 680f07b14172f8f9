"""Login sessions: checking credentials, issuing and revoking tokens."""

from __future__ import annotations

import datetime as dt

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from server.audit import service as audit
from server.auth.models import AuthSession
from server.auth.security import TokenClaims, TokenSigner, new_session_id, verify_password
from server.auth.throttle import LoginThrottle, account_bucket, address_bucket
from server.db import utc_now, write_transaction, writes
from server.errors import NotFoundError
from server.users.models import User


def account_named(*, session: Session, username: str) -> User | None:
    """The account with this username (any case), active or not."""
    return session.scalar(select(User).where(func.lower(User.username) == username.lower()))


def password_matches(user: User | None, password: str) -> bool:
    """True for an active account and its password; the same cost whether or not the account exists."""
    password_hash = user.password_hash if user is not None and user.is_active else None
    return verify_password(password_hash, password)


@writes
def open_login_session(
    *, session: Session, user: User, signer: TokenSigner, lifetime_s: int
) -> tuple[str, dt.datetime]:
    now = utc_now()
    expires_at = (now + dt.timedelta(seconds=lifetime_s)).replace(microsecond=0)
    login = AuthSession(id=new_session_id(), user_id=user.id, created_at=now, expires_at=expires_at)
    session.add(login)
    audit.record(session=session, user_id=user.id, action="login", resource_type="user", resource_id=user.id)
    token = signer.issue(TokenClaims(login.id, user.id, int(expires_at.timestamp())))
    return token, expires_at


@writes
def revoke_login_session(*, session: Session, session_id: str, user_id: int) -> None:
    login = session.get(AuthSession, session_id)
    if login is not None and login.revoked_at is None:
        login.revoked_at = utc_now()
    audit.record(session=session, user_id=user_id, action="logout", resource_type="user", resource_id=user_id)


def unlock_login(
    *, session: Session, throttle: LoginThrottle, username: str | None, address: str | None, actor_id: int | None
) -> list[str]:
    """Lift an address's back-off and/or an account's delay (server.auth.throttle); what was lifted."""
    lifted = []
    if username is not None:
        user = account_named(session=session, username=username)
        if user is None:
            raise NotFoundError("account", username)
        throttle.unlock(session, account_bucket(user.id))
        lifted.append(f"account {user.username}")
    if address is not None:
        throttle.unlock(session, address_bucket(address))
        lifted.append(f"address {address}")
    with write_transaction(session):
        audit.record(session=session, user_id=actor_id, action="unlock_login", resource_type="user",
                     resource_id=None, details={"lifted": lifted})  # fmt: skip
    return lifted
