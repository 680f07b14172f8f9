"""Account requests and answers; password hashes never leave the service."""

from __future__ import annotations

import datetime as dt
from typing import Literal

from pydantic import ConfigDict, Field

from server.api_types import OptionalName, Password, RequestModel, ResponseModel, Username

Role = Literal["admin", "therapist"]


class UserCreate(RequestModel):
    username: Username = Field(examples=["jdoe"])
    password: Password = Field(examples=["correct horse battery"])
    role: Role = Field(examples=["therapist"])
    full_name: OptionalName = Field("", examples=["Jane Doe, PT"])

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {"username": "jdoe", "password": "correct horse battery", "role": "therapist", "full_name": "Jane Doe"}
            ]
        }
    )


class UserUpdate(RequestModel):
    full_name: OptionalName | None = None
    role: Role | None = None
    password: Password | None = None
    is_active: bool | None = None

    model_config = ConfigDict(json_schema_extra={"examples": [{"full_name": "Jane Doe, PT", "role": "therapist"}]})


class UserOut(ResponseModel):
    id: int
    username: str
    full_name: str
    role: Role
    is_active: bool
    created_at: dt.datetime
