"""`POST /auth/login` (public), `POST /auth/logout`, `GET /auth/me`."""

from __future__ import annotations

import math
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Request, Response, status

from server.auth import service, throttle
from server.auth.dependencies import CurrentUser, auth_state, authenticated_claims, current_user
from server.auth.schemas import LoginRequest, LoginResult
from server.auth.security import TokenClaims
from server.db import SessionDep
from server.users.schemas import UserOut

public_router = APIRouter(prefix="/auth", tags=["auth"])
router = APIRouter(prefix="/auth", tags=["auth"], dependencies=[Depends(current_user)])


@public_router.post(
    "/login",
    response_model=LoginResult,
    responses={401: {"description": "Wrong username or password"}, 429: {"description": "Too many failed logins"}},
)
def login(data: LoginRequest, request: Request, response: Response, session: SessionDep) -> LoginResult:
    """Answers with a session cookie (HttpOnly, SameSite=Strict) and the same token as a bearer token."""
    state = auth_state(request)
    settings = request.app.state.settings
    user = service.account_named(session=session, username=data.username)
    # A name that is no account is throttled on its own: its guesses never lock out a real account.
    account = throttle.account_bucket(user.id) if user is not None else throttle.unknown_name_bucket(data.username)
    addresses = [throttle.address_bucket(request.client.host if request.client else "unknown")] if user else []
    retry_after = state.throttle.reserve(session, [account, *addresses])
    if retry_after is not None:
        raise HTTPException(
            status.HTTP_429_TOO_MANY_REQUESTS,
            detail=f"too many failed logins: try again in {math.ceil(retry_after)} s",
            headers={"Retry-After": str(math.ceil(retry_after))},
        )
    matched = service.password_matches(user, data.password)  # first: an unknown name costs the same time
    if not matched or user is None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, detail="wrong username or password")
    state.throttle.succeeded(session, account=account, others=addresses)
    token, expires_at = service.open_login_session(
        session=session, user=user, signer=state.signer, lifetime_s=settings.token_lifetime_s
    )
    response.set_cookie(
        state.cookie_name,
        token,
        max_age=settings.token_lifetime_s,
        httponly=True,
        samesite="strict",
        secure=settings.cookie_secure,
        path="/",
    )
    return LoginResult(access_token=token, expires_at=expires_at, user=UserOut.model_validate(user))


@router.post(
    "/logout",
    status_code=status.HTTP_204_NO_CONTENT,
    responses={409: {"description": "A session is in motion on this console's robot: stop it first"}},
)
def logout(
    request: Request,
    session: SessionDep,
    user: CurrentUser,
    claims: Annotated[TokenClaims, Depends(authenticated_claims)],
) -> Response:
    """Refused while this console's robot runs a session (issue 12, defect 12): stop or pause it first."""
    robot = request.app.state.robot
    active = robot.active_run() if robot is not None else None
    if active is not None:
        raise HTTPException(
            status.HTTP_409_CONFLICT,
            detail=f"robot {robot.robot!r} is in motion (run {active[0]}, session {active[1]}): stop the session "
            "before logging out. The emergency stop on this page works logged out as well.",
        )
    state = auth_state(request)
    state.revoke(claims.session_id)
    service.revoke_login_session(session=session, session_id=claims.session_id, user_id=user.id)
    response = Response(status_code=status.HTTP_204_NO_CONTENT)
    response.delete_cookie(state.cookie_name, path="/", httponly=True, samesite="strict")
    return response


@router.get("/me", response_model=UserOut)
def me(user: CurrentUser) -> UserOut:
    return UserOut.model_validate(user)
