"""Login request and answer."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Literal

from pydantic import ConfigDict, Field, IPvAnyAddress, StringConstraints, model_validator

from server.api_types import NO_NUL_PATTERN, RequestModel, ResponseModel
from server.users.schemas import UserOut

LoginText = Annotated[str, StringConstraints(min_length=1, max_length=256, pattern=NO_NUL_PATTERN)]


class LoginRequest(RequestModel):
    username: LoginText = Field(examples=["admin"])
    password: LoginText = Field(examples=["change-me-now"])

    model_config = ConfigDict(json_schema_extra={"examples": [{"username": "admin", "password": "change-me-now"}]})


class LoginUnlock(RequestModel):
    """What an admin unlocks: a client address's back-off, an account's delay, or both."""

    username: LoginText | None = Field(None, description="The account whose failed logins are forgotten.")
    address: IPvAnyAddress | None = Field(None, description="The client address whose back-off is lifted.")

    model_config = ConfigDict(json_schema_extra={"examples": [{"username": "therapist", "address": "10.0.0.20"}]})

    @model_validator(mode="after")
    def _something(self) -> LoginUnlock:
        if self.username is None and self.address is None:
            raise ValueError("name a username, an address or both")
        return self


class LoginUnlocked(ResponseModel):
    unlocked: list[str]


class LoginResult(ResponseModel):
    access_token: str
    token_type: Literal["bearer"] = "bearer"
    expires_at: dt.datetime
    user: UserOut
