"""`/users`: account management, admin only."""

from __future__ import annotations

from fastapi import APIRouter, Depends, status

from server.api_types import IdPath, Limit, Offset
from server.auth.dependencies import AdminUser, require_admin
from server.db import SessionDep
from server.users import service
from server.users.schemas import UserCreate, UserOut, UserUpdate

router = APIRouter(prefix="/users", tags=["users"], dependencies=[Depends(require_admin)])


@router.get("", response_model=list[UserOut])
def list_users(session: SessionDep, limit: Limit = 100, offset: Offset = 0) -> list[UserOut]:
    return [UserOut.model_validate(u) for u in service.list_users(session=session, limit=limit, offset=offset)]


@router.post("", response_model=UserOut, status_code=status.HTTP_201_CREATED)
def create_user(data: UserCreate, session: SessionDep, admin: AdminUser) -> UserOut:
    return UserOut.model_validate(service.create_user(session=session, data=data, actor_id=admin.id))


@router.get("/{user_id}", response_model=UserOut)
def get_user(user_id: IdPath, session: SessionDep) -> UserOut:
    return UserOut.model_validate(service.get_user(session=session, user_id=user_id))


@router.patch("/{user_id}", response_model=UserOut)
def update_user(user_id: IdPath, data: UserUpdate, session: SessionDep, admin: AdminUser) -> UserOut:
    return UserOut.model_validate(service.update_user(session=session, user_id=user_id, data=data, actor_id=admin.id))
