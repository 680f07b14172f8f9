"""Who may see and change what (docs/service.md, "Who may see and change what"): object-level authorisation
in one place.

A patient's record and everything hanging off it (prescriptions, bookings, series, runs, events, notes,
reviews, reports, exports, the telemetry of a session) belong to the patient's **care team**; admins see
and change everything. `object_access` is the router dependency that checks every object id in a route's
path; `require_patient` checks an id from a body; `restrict_to_care` narrows a list query. Everything the
caller may not see answers 404 with the same words whether it exists or not. Routes whose path holds no
object id declare their rule in `UNSCOPED_ROUTES` (tests/server/test_object_access.py walks the route
table: a route with neither fails it).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, Any, TypeVar

from fastapi import Depends, HTTPException, Request, status
from sqlalchemy import Select, select
from sqlalchemy.orm import InstrumentedAttribute, Session

from server.api_types import MAX_ID
from server.auth.dependencies import CurrentUser, authenticated_claims, unauthorized, user_for_claims
from server.auth.security import TokenClaims
from server.db import Database, SessionDep
from server.errors import NotFoundError
from server.patients.models import CareTeamMember, Patient
from server.prescriptions.models import Prescription
from server.robotd.models import SessionRun
from server.scheduling.models import ScheduledSession
from server.users.models import User

ADMIN_ROLE = "admin"
NOT_IN_CARE = "or is not in the care of your account (ask a member of the patient's care team or an admin to add you)"


def _patient(session: Session, patient_id: int) -> int | None:
    return session.scalar(select(Patient.id).where(Patient.id == patient_id))


def _patient_of_prescription(session: Session, prescription_id: int) -> int | None:
    return session.scalar(select(Prescription.patient_id).where(Prescription.id == prescription_id))


def _patient_of_booking(session: Session, session_id: int) -> int | None:
    return session.scalar(select(ScheduledSession.patient_id).where(ScheduledSession.id == session_id))


def _patient_of_series(session: Session, series_id: int) -> int | None:
    return session.scalar(select(ScheduledSession.patient_id).where(ScheduledSession.series_id == series_id).limit(1))


def _patient_of_run(session: Session, run_id: int) -> int | None:
    return session.scalar(
        select(ScheduledSession.patient_id)
        .join(SessionRun, SessionRun.scheduled_session_id == ScheduledSession.id)
        .where(SessionRun.id == run_id)
    )


# Path parameter -> (how a 404 names the object, the patient it belongs to). Every route with one of these
# in its path is checked; a new kind of object id needs an entry here.
PATIENT_OBJECTS: dict[str, tuple[str, Callable[[Session, int], int | None]]] = {
    "patient_id": ("patient", _patient),
    "prescription_id": ("prescription", _patient_of_prescription),
    "session_id": ("session", _patient_of_booking),
    "series_id": ("series", _patient_of_series),
    "run_id": ("session run", _patient_of_run),
}
# A therapist's own calendar and its subscription link: that therapist or an admin (403, the rule in words).
SELF_OBJECTS = ("therapist_id",)

# Routes without an object id in their path, and why each is safe (method, path under /api/v1).
PUBLIC = "public"
ANY_USER = "any logged-in user: no patient data"
ADMIN_ONLY = "admin only"
LIST_IN_CARE = "a list narrowed to the caller's care teams (admins: all)"
BODY_PATIENT = "the patient named in the body must be in the caller's care"
STOP = "anyone logged in may stop or pause motion: a stop is never refused"
UNSCOPED_ROUTES: dict[tuple[str, str], str] = {
    ("GET", "/health"): PUBLIC,
    ("POST", "/auth/login"): PUBLIC,
    ("POST", "/auth/logout"): ANY_USER,
    ("GET", "/auth/me"): ANY_USER,
    ("POST", "/auth/unlock"): ADMIN_ONLY,
    ("POST", "/estop"): "public: anyone at the console may stop the robot",
    ("GET", "/calendar/{token}.ics"): "public: the secret link is the credential of one therapist's own feed",
    ("GET", "/users"): ADMIN_ONLY,
    ("POST", "/users"): ADMIN_ONLY,
    ("GET", "/users/{user_id}"): ADMIN_ONLY,
    ("PATCH", "/users/{user_id}"): ADMIN_ONLY,
    ("GET", "/audit"): ADMIN_ONLY,
    ("GET", "/patients"): LIST_IN_CARE,
    ("POST", "/patients"): "any logged-in user; the creator joins the new record's care team",
    ("GET", "/prescriptions"): LIST_IN_CARE,
    ("POST", "/prescriptions"): BODY_PATIENT,
    ("POST", "/prescriptions/previews"): "the patient named in the body, if any, must be in the caller's care",
    ("GET", "/prescriptions/previews/{preview_id}"): "the user who started the preview job only (others: 404)",
    ("GET", "/sessions"): LIST_IN_CARE,
    ("POST", "/sessions"): BODY_PATIENT,
    ("GET", "/schedule/week"): "every booking's time and robot (free/busy); patient and notes only for the "
    "caller's care teams",
    ("GET", "/reviews/pending"): "the robot's pending acknowledgement (a safety interlock); its notes only for "
    "the run's care team",
    ("GET", "/exports/bulk"): "pseudonymised runs of the caller's care teams (admins: all)",
    ("POST", "/exports/bulk/jobs"): "pseudonymised runs of the caller's care teams (admins: all)",
    ("GET", "/exports/jobs/{job_id}"): "the user who started the export job only (others: 404)",
    ("GET", "/exports/jobs/{job_id}/download"): "the user who started the export job only (others: 404)",
    ("GET", "/robot/state"): ANY_USER,
    ("POST", "/robot/reset"): ANY_USER,
    ("POST", "/sessions/{session_id}/pause"): STOP,
    ("POST", "/sessions/{session_id}/stop"): STOP,
    ("GET", "/viz"): ANY_USER,
    ("POST", "/viz/live"): ANY_USER,
    ("POST", "/viz/camera"): ANY_USER,
    ("POST", "/viz/controls"): ANY_USER,
    ("POST", "/viz/replay"): "the run named in the body must be in the caller's care",
    ("POST", "/viz/figure"): BODY_PATIENT,
    ("GET", "/viz/view/"): "any logged-in user: the 3D view shows no name or record",
    ("GET", "/viz/view/{path:path}"): "any logged-in user: the 3D view shows no name or record",
    ("WEBSOCKET", "/viz/view"): "any logged-in user: the 3D view shows no name or record",
}


def is_admin(user: User) -> bool:
    return user.role == ADMIN_ROLE


def in_care(session: Session, user: User, patient_id: int) -> bool:
    """Whether `user` may see and change this patient's record and everything hanging off it."""
    return is_admin(user) or session.get(CareTeamMember, (patient_id, user.id)) is not None


def not_found(resource: str, resource_id: object) -> NotFoundError:
    error = NotFoundError(resource, resource_id)
    error.args = (f"{resource} {resource_id} does not exist {NOT_IN_CARE}",)
    return error


def require_patient(session: Session, user: User, patient_id: int, resource: str = "patient") -> None:
    """For an id from a body or query: 404 unless the patient exists and is in the caller's care."""
    if is_admin(user):
        return
    if _patient(session, patient_id) is None or not in_care(session, user, patient_id):
        raise not_found(resource, patient_id)


def require_object(session: Session, user: User, parameter: str, object_id: int) -> None:
    """The object named `parameter` (`run_id`, `session_id`, ...) must belong to a patient in the caller's care."""
    if is_admin(user):
        return
    resource, patient_of = PATIENT_OBJECTS[parameter]
    patient_id = patient_of(session, object_id)
    if patient_id is None or not in_care(session, user, patient_id):
        raise not_found(resource, object_id)


def check_path(session: Session, user: User, path_params: dict[str, Any]) -> None:
    for name, raw in path_params.items():
        if name in SELF_OBJECTS:
            _require_self(user, name, raw)
            continue
        if name not in PATIENT_OBJECTS:
            continue
        try:
            object_id = int(raw)
        except (TypeError, ValueError):
            continue  # not an id: the route's own validation answers 422
        if 1 <= object_id <= MAX_ID:
            require_object(session, user, name, object_id)


def _require_self(user: User, name: str, raw: Any) -> None:
    if is_admin(user) or str(raw) == str(user.id):
        return
    raise HTTPException(
        status.HTTP_403_FORBIDDEN,
        detail=f"{name} = {raw}: only that therapist or an admin may read or manage this calendar",
    )


def object_access(request: Request, session: SessionDep, user: CurrentUser) -> None:
    """Router dependency: every object id in the path belongs to a patient in the caller's care (admins: all)."""
    check_path(session, user, request.path_params)


def object_access_own_session(request: Request, claims: Annotated[TokenClaims, Depends(authenticated_claims)]) -> None:
    """`object_access` in a database session of its own that ends before the route runs: for motion
    commands, which hold no database session while the robot daemon works."""
    database: Database = request.app.state.database
    with database.session() as session:
        user = user_for_claims(session, claims)
        if user is None:
            raise unauthorized("login session ended: log in again")
        check_path(session, user, request.path_params)


ObjectAccess = Depends(object_access)

Q = TypeVar("Q", bound=Select[Any])


def restrict_to_care(query: Q, patient_column: InstrumentedAttribute[int], user: User) -> Q:
    """`query` narrowed to rows whose patient is in the caller's care (unchanged for admins)."""
    if is_admin(user):
        return query
    return query.where(patient_column.in_(select(CareTeamMember.patient_id).where(CareTeamMember.user_id == user.id)))


def patients_in_care(session: Session, user: User, patient_ids: set[int]) -> set[int]:
    """Which of `patient_ids` are in the caller's care."""
    if is_admin(user) or not patient_ids:
        return set(patient_ids)
    return set(
        session.scalars(
            select(CareTeamMember.patient_id).where(
                CareTeamMember.user_id == user.id, CareTeamMember.patient_id.in_(patient_ids)
            )
        )
    )
