"""Audit-log answers."""

from __future__ import annotations

import datetime as dt
from typing import Any

from server.api_types import ResponseModel


class AuditEntryOut(ResponseModel):
    id: int
    utc: dt.datetime
    user_id: int | None
    action: str
    resource_type: str
    resource_id: int | None
    details: dict[str, Any]
