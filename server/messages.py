"""Typed messages between the console's processes, and the one codec for refusals.

Three boundaries, each with its commands and its replies:
- a web process ↔ its robot daemon (a Unix socket, one JSON message a line): `DaemonRequest`, answered
  by `DaemonReply`; the daemon also pushes `DaemonPush` to every linked console;
- the robot daemon ↔ its planning process (a pipe): `PlanRequest`, answered by `PlanProgress` messages,
  then `PlanReady` or a `Refusal`;
- the robot daemon ↔ its real-time worker (a pipe): `WorkerRequest` carrying a `WorkerCommand`, answered
  by `WorkerReply`.

The pipes carry the structs pickled (a plan is numpy arrays); the socket carries them as JSON. A refusal
crosses every boundary as one `Refusal`: it keeps every field of the error it was made from, and
`Refusal.error()` rebuilds that error on the other side.
"""

from __future__ import annotations

import socket
from collections.abc import Callable
from typing import Any, ClassVar, Literal, NamedTuple

import msgspec

from core.errors import InvalidValueError
from core.plan.prescription import PrescriptionError
from core.plan.rejection import PrescriptionRejected
from server.errors import ConflictError, InvalidFieldError, NotFoundError, WorkerUnavailableError
from server.jsonable import to_jsonable
from server.realtime.supervisor import TransitionRefused


class CommandRefused(RuntimeError):  # noqa: N818 — a refusal, not a malfunction
    """The worker refused a command (wrong state, bad request); the message says why."""


class RemoteError(RuntimeError):
    """An unexpected error in another process, with its type's name: a malfunction, not a refusal."""

    def __init__(self, type_name: str, message: str) -> None:
        self.type_name = type_name
        super().__init__(f"{type_name}: {message}")


# --- refusals -----------------------------------------------------------------------------------------


class Refusal(msgspec.Struct, frozen=True, kw_only=True):
    """An error as it crosses a process boundary: its kind, its message and every field it carries."""

    kind: str  # one of REFUSAL_KINDS, or "error" for anything else
    message: str
    fields: dict[str, Any] = {}

    def error(self) -> Exception:
        """The error this refusal was made from (or `RemoteError` for an unexpected one)."""
        known = _KINDS.get(self.kind)
        if known is None:
            return RemoteError(str(self.fields.get("type_name", self.kind)), self.message)
        return known.rebuild(self.fields, self.message)


class _Kind(NamedTuple):
    error_type: type[BaseException]
    fields: Callable[[Any], dict[str, Any]]
    rebuild: Callable[[dict[str, Any], str], Exception]


def _field_value_limit(error: Any) -> dict[str, Any]:
    return {"field": error.field, "value": to_jsonable(error.value), "limit": error.limit}


def _transition_fields(error: Any) -> dict[str, Any]:
    state = getattr(error, "state", None)
    return {"command": getattr(error, "command", None), "state": getattr(state, "label", state)}


# Most specific first: the first kind the error is an instance of names it.
_KINDS: dict[str, _Kind] = {
    "prescription_rejected": _Kind(
        PrescriptionRejected,
        lambda error: to_jsonable(error.to_dict()),
        lambda fields, _message: PrescriptionRejected.from_dict(fields),
    ),
    "prescription_invalid": _Kind(
        PrescriptionError, _field_value_limit, lambda f, _m: PrescriptionError(f["field"], f["value"], f["limit"])
    ),
    "invalid_value": _Kind(
        InvalidValueError, _field_value_limit, lambda f, _m: InvalidValueError(f["field"], f["value"], f["limit"])
    ),
    "invalid_field": _Kind(
        InvalidFieldError,
        lambda error: {**_field_value_limit(error), "details": to_jsonable(error.details)},
        lambda f, _m: InvalidFieldError(f["field"], f["value"], f["limit"], details=f.get("details")),
    ),
    "not_found": _Kind(
        NotFoundError,
        lambda error: {"resource": error.resource, "resource_id": to_jsonable(error.resource_id)},
        lambda f, _m: NotFoundError(f["resource"], f["resource_id"]),
    ),
    "conflict": _Kind(
        ConflictError, lambda error: {"field": error.field}, lambda f, m: ConflictError(m, field=f.get("field"))
    ),
    "unavailable": _Kind(WorkerUnavailableError, lambda _error: {}, lambda _f, m: WorkerUnavailableError(m)),
    "command_refused": _Kind(CommandRefused, _transition_fields, lambda _f, m: CommandRefused(m)),
}
REFUSAL_KINDS = tuple(_KINDS)


def refusal_of(error: BaseException) -> Refusal:
    """`error` as a `Refusal` (the worker's `TransitionRefused` crosses as `command_refused`)."""
    if isinstance(error, TransitionRefused):
        return Refusal(kind="command_refused", message=str(error), fields=_transition_fields(error))
    for name, kind in _KINDS.items():
        if isinstance(error, kind.error_type):
            return Refusal(kind=name, message=str(error), fields=kind.fields(error))
    return Refusal(kind="error", message=str(error), fields={"type_name": type(error).__name__})


# --- web process ↔ robot daemon ----------------------------------------------------------------------


class DaemonNames(msgspec.Struct, frozen=True, kw_only=True):
    """Where a console finds the daemon's status and the worker's shared memory."""

    robot: str
    pid: int
    status_name: str | None = None
    control_name: str | None = None
    state_name: str | None = None
    realtime: dict[str, Any] | None = None
    link_id: str | None = None  # a persistent link's id (the hello's answer only)


class _DaemonRequest(msgspec.Struct, frozen=True, kw_only=True, tag_field="cmd"):
    reply_type: ClassVar[Any] = None


class Hello(_DaemonRequest, frozen=True, kw_only=True, tag="hello"):
    """Opens a console's link (`persistent`: kept open, with beats) or asks for the daemon's names."""

    persistent: bool = False
    web_pid: int | None = None
    console: str | None = None
    reply_type: ClassVar[Any] = DaemonNames


class StartSession(_DaemonRequest, frozen=True, kw_only=True, tag="start"):
    session_id: int
    user_id: int
    link_id: str | None = None
    estop_generation: int | None = None  # the stops requested when the start was asked for
    control_name: str | None = None  # the worker's control block that count was read from
    reply_type: ClassVar[Any] = int  # the run's id


class ControlRun(_DaemonRequest, frozen=True, kw_only=True, tag="control"):
    session_id: int
    command: Literal["pause", "resume", "stop"]
    user_id: int
    credential: str
    reply_type: ClassVar[Any] = dict[str, Any] | None  # the run as decided; None: a stop cancelled its start


class ResetRobot(_DaemonRequest, frozen=True, kw_only=True, tag="reset"):
    user_id: int


class NoteEmergencyStop(_DaemonRequest, frozen=True, kw_only=True, tag="estop_note"):
    user_id: int | None
    authenticated: bool
    credential: str
    reply_type: ClassVar[Any] = list[int]  # the runs it stopped


class AuditListenerStop(_DaemonRequest, frozen=True, kw_only=True, tag="estop_audit"):
    """The stop listener's stop, after its answer: who asked (its token, checked here)."""

    token: str | None
    outcome: str
    reply_type: ClassVar[Any] = list[int]


class ActiveRun(_DaemonRequest, frozen=True, kw_only=True, tag="active_run"):
    reply_type: ClassVar[Any] = tuple[int, int] | None  # (run id, session id)


class PlanStatus(_DaemonRequest, frozen=True, kw_only=True, tag="plan_status"):
    session_id: int
    reply_type: ClassVar[Any] = dict[str, Any] | None


class Metrics(_DaemonRequest, frozen=True, kw_only=True, tag="metrics"):
    reply_type: ClassVar[Any] = str  # Prometheus text


DaemonRequest = (
    Hello
    | StartSession
    | ControlRun
    | ResetRobot
    | NoteEmergencyStop
    | AuditListenerStop
    | ActiveRun
    | PlanStatus
    | Metrics
)


class DaemonReply(msgspec.Struct, frozen=True, kw_only=True):
    result: Any = None
    refusal: Refusal | None = None


class EventsPush(msgspec.Struct, frozen=True, kw_only=True, tag_field="push", tag="events"):
    events: list[dict[str, Any]]


class ReadyPush(msgspec.Struct, frozen=True, kw_only=True, tag_field="push", tag="ready"):
    """A (new) worker runs: its shared memory's names."""

    names: DaemonNames


DaemonPush = EventsPush | ReadyPush

_requests = msgspec.json.Decoder(DaemonRequest)
_replies = msgspec.json.Decoder(DaemonReply)
_pushes = msgspec.json.Decoder(DaemonPush)


def _plain(value: Any) -> Any:
    """numpy values as plain numbers and lists; anything else msgspec cannot write, as its text."""
    plain = to_jsonable(value)
    return str(value) if plain is value else plain


_encoder = msgspec.json.Encoder(enc_hook=_plain)


def encode_line(message: msgspec.Struct) -> bytes:
    """One message as a line of JSON."""
    return _encoder.encode(message) + b"\n"


def decode_request(line: bytes) -> DaemonRequest:
    """A console's request; refuses one the daemon does not know, naming what was wrong."""
    request: DaemonRequest = _requests.decode(line)
    return request


def decode_reply(line: bytes, request: _DaemonRequest) -> Any:
    """The result of `request`, typed as its `reply_type`; raises the refusal it carries."""
    reply = _replies.decode(line)
    if reply.refusal is not None:
        raise reply.refusal.error()
    if request.reply_type is None:
        return None
    return msgspec.convert(reply.result, request.reply_type)


def exchange(socket_path: str, request: _DaemonRequest, timeout_s: float) -> Any:
    """One request to the daemon listening on `socket_path` and its typed result; raises the refusal it
    answered, `OSError` if it could not be reached, `EOFError` if it closed the connection unanswered."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as connection:
        connection.settimeout(timeout_s)
        connection.connect(socket_path)
        connection.sendall(encode_line(request))
        line = connection.makefile("rb").readline()
    if not line:
        raise EOFError("the robot daemon closed the connection without an answer")
    return decode_reply(line, request)


def decode_push(line: bytes) -> DaemonPush:
    push: DaemonPush = _pushes.decode(line)
    return push


def decode_names(result: Any) -> DaemonNames:
    return msgspec.convert(result, DaemonNames)


# --- robot daemon ↔ planning process ------------------------------------------------------------------


class PlanRequest(msgspec.Struct, frozen=True, kw_only=True):
    prescription: dict[str, Any]
    patient: dict[str, Any] | None


class PlanProgress(msgspec.Struct, frozen=True):
    fraction: float  # of the plan done, 0–1


class PlanReady(msgspec.Struct, frozen=True):
    plan: Any  # core.plan.build.PrescriptionPlan
    report: dict[str, Any]  # its check report


# --- robot daemon ↔ real-time worker -----------------------------------------------------------------


class LoadPlan(msgspec.Struct, frozen=True, kw_only=True):
    plan: Any  # core.plan.build.PrescriptionPlan, checked
    report: dict[str, Any]
    estop_generation: int | None = None


class StartMotion(msgspec.Struct, frozen=True, kw_only=True):
    approach: Any  # core.plan.motion.Transition, checked
    estop_generation: int | None = None


class PauseMotion(msgspec.Struct, frozen=True):
    transition: Any  # core.plan.motion.Transition, checked


class ResumeMotion(msgspec.Struct, frozen=True):
    transition: Any


class StopMotion(msgspec.Struct, frozen=True):
    pass


class ResetFaults(msgspec.Struct, frozen=True):
    pass


class EmergencyStop(msgspec.Struct, frozen=True):
    """The pipe's copy of a stop already latched through shared memory."""


class RealtimeSetup(msgspec.Struct, frozen=True):
    """Asks for the worker's CPU, SCHED_FIFO priority and refusals."""


class ServiceLost(msgspec.Struct, frozen=True):
    reason: str


class RecordingFailed(msgspec.Struct, frozen=True):
    details: dict[str, Any]


class LatchFault(msgspec.Struct, frozen=True):
    """A stop that happened before this worker (`worker_lost`, `daemon_lost`), shown as a latched fault."""

    reason: str
    details: dict[str, Any]


class Shutdown(msgspec.Struct, frozen=True):
    pass


WorkerCommand = (
    LoadPlan
    | StartMotion
    | PauseMotion
    | ResumeMotion
    | StopMotion
    | ResetFaults
    | EmergencyStop
    | RealtimeSetup
    | ServiceLost
    | RecordingFailed
    | LatchFault
    | Shutdown
)


class WorkerRequest(msgspec.Struct, frozen=True):
    request_id: int
    command: WorkerCommand


class WorkerReply(msgspec.Struct, frozen=True):
    request_id: int
    result: Any = None
    refusal: Refusal | None = None
