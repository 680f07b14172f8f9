"""`GET /audit` (admin only)."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query

from server.api_types import MAX_ID, Limit, Offset
from server.audit import service
from server.audit.schemas import AuditEntryOut
from server.auth.dependencies import require_admin
from server.db import SessionDep

router = APIRouter(prefix="/audit", tags=["audit"], dependencies=[Depends(require_admin)])


@router.get("", response_model=list[AuditEntryOut])
def list_audit_entries(
    session: SessionDep,
    resource_type: Annotated[str | None, Query(max_length=32, pattern=r"^[a-z_]+$")] = None,
    resource_id: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    user_id: Annotated[int | None, Query(ge=1, le=MAX_ID)] = None,
    limit: Limit = 100,
    offset: Offset = 0,
) -> list[AuditEntryOut]:
    entries = service.list_entries(
        session=session,
        resource_type=resource_type,
        resource_id=resource_id,
        user_id=user_id,
        limit=limit,
        offset=offset,
    )
    return [AuditEntryOut.model_validate(entry) for entry in entries]
