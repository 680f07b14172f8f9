"""Field types shared by the request schemas of every domain, so that bad input is a 422 naming the field.

Strings refuse NUL characters (PostgreSQL cannot store them), ids and page sizes are bounded (SQLite
integers are 64-bit), and floats must be finite and normal (`core.validation`).
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Path, Query
from pydantic import BaseModel, ConfigDict, StringConstraints

from core.validation import StrictModel

NO_NUL_PATTERN = r"^[^\x00]*$"
MAX_ID = 2**31 - 1


def _text(max_length: int, min_length: int) -> StringConstraints:
    return StringConstraints(
        strip_whitespace=True, min_length=min_length, max_length=max_length, pattern=NO_NUL_PATTERN
    )


# Stripped strings without NUL characters, of bounded length.
Label = Annotated[str, _text(64, 1)]
Name = Annotated[str, _text(200, 1)]
OptionalName = Annotated[str, _text(200, 0)]
LongText = Annotated[str, _text(10_000, 0)]
Password = Annotated[str, StringConstraints(min_length=8, max_length=256, pattern=NO_NUL_PATTERN)]
Username = Annotated[str, StringConstraints(min_length=3, max_length=64, pattern=r"^[A-Za-z0-9_.@-]+$")]

IdPath = Annotated[int, Path(ge=1, le=MAX_ID, description="Record id.")]
Limit = Annotated[int, Query(ge=1, le=500, description="Page size.")]
Offset = Annotated[int, Query(ge=0, le=MAX_ID, description="Rows to skip.")]


class RequestModel(StrictModel):
    """Request bodies: unknown fields, non-finite and subnormal numbers are refused at their field."""


class ResponseModel(BaseModel):
    model_config = ConfigDict(from_attributes=True)
