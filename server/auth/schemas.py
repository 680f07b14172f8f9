"""Login request and answer."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Literal

from pydantic import ConfigDict, Field, StringConstraints

from server.api_types import NO_NUL_PATTERN, RequestModel, ResponseModel
from server.users.schemas import UserOut

LoginText = Annotated[str, StringConstraints(min_length=1, max_length=256, pattern=NO_NUL_PATTERN)]


class LoginRequest(RequestModel):
    username: LoginText = Field(examples=["admin"])
    password: LoginText = Field(examples=["change-me-now"])

    model_config = ConfigDict(json_schema_extra={"examples": [{"username": "admin", "password": "change-me-now"}]})


class LoginResult(ResponseModel):
    access_token: str
    token_type: Literal["bearer"] = "bearer"
    expires_at: dt.datetime
    user: UserOut
