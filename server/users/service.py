"""Account service functions: keyword-only, taking the ORM session explicitly, committing once."""

from __future__ import annotations

from sqlalchemy import func, select, update
from sqlalchemy.orm import Session

from server.audit import service as audit
from server.auth.models import AuthSession
from server.auth.security import hash_password
from server.db import utc_now, writes
from server.errors import ConflictError, InvalidFieldError, NotFoundError
from server.users.models import ROLES, User
from server.users.schemas import UserCreate, UserUpdate


@writes
def create_user(*, session: Session, data: UserCreate, actor_id: int | None) -> User:
    if data.role not in ROLES:
        raise InvalidFieldError("role", data.role, f"must be one of {ROLES}")
    if session.scalar(select(User.id).where(func.lower(User.username) == data.username.lower())) is not None:
        raise ConflictError(f"username {data.username!r} is taken", field="username")
    user = User(
        username=data.username, full_name=data.full_name, role=data.role, password_hash=hash_password(data.password)
    )
    session.add(user)
    session.flush()
    audit.record(session=session, user_id=actor_id, action="create", resource_type="user", resource_id=user.id)
    return user


def get_user(*, session: Session, user_id: int) -> User:
    user = session.get(User, user_id)
    if user is None:
        raise NotFoundError("user", user_id)
    return user


def list_users(*, session: Session, limit: int = 100, offset: int = 0) -> list[User]:
    return list(session.scalars(select(User).order_by(User.id).limit(limit).offset(offset)))


def count_users(*, session: Session) -> int:
    return session.scalar(select(func.count()).select_from(User)) or 0


def _active_admins(session: Session) -> int:
    return session.scalar(select(func.count()).where(User.role == "admin", User.is_active.is_(True))) or 0


@writes
def update_user(*, session: Session, user_id: int, data: UserUpdate, actor_id: int | None) -> User:
    user = get_user(session=session, user_id=user_id)
    changes = data.model_dump(exclude_unset=True, exclude_none=True)
    loses_admin = (
        user.role == "admin"
        and user.is_active
        and (changes.get("role", "admin") != "admin" or changes.get("is_active", True) is False)
    )
    if loses_admin and _active_admins(session) <= 1:
        raise ConflictError("this is the last active admin: keep at least one", field="role")
    if "password" in changes:
        user.password_hash = hash_password(changes.pop("password"))
        changes["password"] = "changed"
    for name in ("full_name", "role", "is_active"):
        if name in changes:
            setattr(user, name, changes[name])
    if changes.get("is_active") is False or "password" in changes:
        # A deactivated account or a changed password ends every open login session of that account.
        session.execute(
            update(AuthSession)
            .where(AuthSession.user_id == user.id, AuthSession.revoked_at.is_(None))
            .values(revoked_at=utc_now())
        )
    audit.record(
        session=session,
        user_id=actor_id,
        action="update",
        resource_type="user",
        resource_id=user.id,
        details={"fields": sorted(changes)},
    )
    return user
