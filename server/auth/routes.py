"""`POST /auth/login` (public), `POST /auth/logout`, `GET /auth/me`."""

from __future__ import annotations

import math
from typing import Annotated

from fastapi import APIRouter, Depends, HTTPException, Request, Response, status
from fastapi.concurrency import run_in_threadpool

from server.auth import service, throttle
from server.auth.dependencies import AdminUser, CurrentUser, auth_state, authenticated_claims, current_user
from server.auth.schemas import LoginRequest, LoginResult, LoginUnlock, LoginUnlocked
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
async def login(data: LoginRequest, request: Request, response: Response, session: SessionDep) -> LoginResult:
    """Answers with a session cookie (HttpOnly, SameSite=Strict) and the same token as a bearer token. The
    client address backs off after repeated failures (429); an account's failures from anywhere only delay
    the next attempts on it (server.auth.throttle)."""
    state = auth_state(request)
    settings = request.app.state.settings
    user = await run_in_threadpool(lambda: service.account_named(session=session, username=data.username))
    # A name that is no account has a count of its own, with the same delays: its existence does not show.
    account = throttle.account_bucket(user.id) if user is not None else throttle.unknown_name_bucket(data.username)
    # The connecting address; X-Forwarded-For has set it only if the sender is a trusted proxy (server.app).
    addresses = [throttle.address_bucket(request.client.host if request.client else "unknown")]
    retry_after = await run_in_threadpool(state.throttle.reserve, session, addresses)
    if retry_after is not None:
        raise HTTPException(
            status.HTTP_429_TOO_MANY_REQUESTS,
            detail=f"too many failed logins from this address: try again in {math.ceil(retry_after)} s",
            headers={"Retry-After": str(math.ceil(retry_after))},
        )
    delay_s = await run_in_threadpool(state.throttle.delay_s, session, account)
    if delay_s > 0:
        await state.throttle.sleep(delay_s)  # on the event loop: a delayed attempt holds no thread
    matched = await run_in_threadpool(service.password_matches, user, data.password)  # same cost for any name
    if not matched or user is None:
        await run_in_threadpool(state.throttle.failed, session, account)
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, detail="wrong username or password")
    await run_in_threadpool(lambda: state.throttle.succeeded(session, account=account, others=addresses))
    token, expires_at = await run_in_threadpool(
        lambda: service.open_login_session(
            session=session, user=user, signer=state.signer, lifetime_s=settings.token_lifetime_s
        )
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


@router.post("/unlock", response_model=LoginUnlocked, responses={404: {"description": "No such account"}})
def unlock(data: LoginUnlock, request: Request, session: SessionDep, admin: AdminUser) -> LoginUnlocked:
    """Admins: lift a client address's back-off and/or forget an account's failed logins (its delay)."""
    lifted = service.unlock_login(
        session=session,
        throttle=auth_state(request).throttle,
        username=data.username,
        address=str(data.address) if data.address is not None else None,
        actor_id=admin.id,
    )
    return LoginUnlocked(unlocked=lifted)
