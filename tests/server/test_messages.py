"""Issue 21 §5 / defect 8: typed messages at the process boundaries, and one refusal codec that keeps
every field, across the pipes (pickled) and the daemon's socket (JSON)."""

from __future__ import annotations

import pickle
from typing import Any

import msgspec
import pytest

from core.errors import InvalidValueError
from core.plan.prescription import PrescriptionError
from core.plan.rejection import PrescriptionRejected
from server.errors import ConflictError, InvalidFieldError, NotFoundError, WorkerUnavailableError
from server.messages import (
    REFUSAL_KINDS,
    CommandRefused,
    ControlRun,
    DaemonNames,
    DaemonReply,
    Hello,
    RemoteError,
    StartSession,
    WorkerReply,
    decode_reply,
    decode_request,
    encode_line,
    refusal_of,
)
from server.realtime.supervisor import TransitionRefused
from server.realtime.telemetry import SupervisorState
from server.robotd.runs import refused

BREACHES = {"kinematic_breaches": {"stroke": [[1.25, 1.5]]}, "singularity": {"worst_condition": 41.2, "at_s": 1.3}}
REJECTED = PrescriptionRejected(3, 1.25, "stroke_max_m", 0.412, "slider 4 over its stroke", BREACHES)


def fields_of(error: BaseException) -> dict[str, Any]:
    return {key: value for key, value in vars(error).items() if not key.startswith("_")}


ERRORS: list[BaseException] = [
    REJECTED,
    PrescriptionError("segments[0].duration_s", 0.2, "must be >= 1 s"),
    InvalidValueError("cutoff_hz", -1.0, "must be > 0"),
    InvalidFieldError("segments[3]", 0.412, "stroke_max_m at t = 1.250 s", details={"segment": 3, **BREACHES}),
    NotFoundError("session", 42),
    ConflictError("robot 'R1' is busy starting session 7", field="robot"),
    WorkerUnavailableError("robot 'R1' is starting"),
    CommandRefused("reset: not accepted in state idle"),
]


def through_the_pipe(reply: WorkerReply) -> WorkerReply:
    copy: WorkerReply = pickle.loads(pickle.dumps(reply))
    return copy


def through_the_socket(reply: DaemonReply) -> Exception:
    with pytest.raises(Exception) as raised:
        decode_reply(encode_line(reply), StartSession(session_id=1, user_id=1))
    return raised.value  # type: ignore[return-value]


@pytest.mark.parametrize("error", ERRORS, ids=lambda error: type(error).__name__)
def test_every_refusal_crosses_both_transports_with_every_field(error: BaseException) -> None:
    refusal = refusal_of(error)
    assert refusal.kind in REFUSAL_KINDS
    for rebuilt in (
        through_the_pipe(WorkerReply(1, refusal=refusal)).refusal.error(),  # type: ignore[union-attr]
        through_the_socket(DaemonReply(refusal=refusal)),
    ):
        assert type(rebuilt) is type(error)
        assert str(rebuilt) == str(error)
        assert fields_of(rebuilt) == fields_of(error)


def test_a_refused_plan_keeps_its_details_on_the_way_to_the_browser() -> None:
    """The daemon answers the web side with the start's refusal as a 422 field error: every breach the check
    found and the singularity report go with it (they were dropped before)."""
    rebuilt = through_the_socket(DaemonReply(refusal=refusal_of(refused(REJECTED))))
    assert isinstance(rebuilt, InvalidFieldError)
    assert rebuilt.field == "segments[3]" and rebuilt.value == 0.412
    assert rebuilt.details == {"segment": 3, "time_s": 1.25, **BREACHES}


def test_the_workers_refusal_of_a_transition_is_a_command_refusal_with_its_state() -> None:
    refusal = refusal_of(TransitionRefused("pause", SupervisorState.IDLE, "nothing runs"))
    assert refusal.fields == {"command": "pause", "state": SupervisorState.IDLE.label}
    rebuilt = through_the_pipe(WorkerReply(1, refusal=refusal)).refusal.error()  # type: ignore[union-attr]
    assert isinstance(rebuilt, CommandRefused) and "nothing runs" in str(rebuilt)


def test_an_unexpected_error_crosses_as_a_malfunction_with_its_type() -> None:
    rebuilt = through_the_socket(DaemonReply(refusal=refusal_of(KeyError("session_id"))))
    assert isinstance(rebuilt, RemoteError) and rebuilt.type_name == "KeyError"


def test_replies_are_typed_by_their_request() -> None:
    assert decode_reply(encode_line(DaemonReply(result=17)), StartSession(session_id=1, user_id=1)) == 17
    with pytest.raises(msgspec.ValidationError, match="Expected `int`"):
        decode_reply(encode_line(DaemonReply(result="17 runs")), StartSession(session_id=1, user_id=1))


def test_a_console_link_opens_with_the_daemons_names() -> None:
    names = DaemonNames(robot="R1", pid=41, status_name="st", control_name="ctl", state_name="sl", link_id="k")
    assert decode_reply(encode_line(DaemonReply(result=names)), Hello(persistent=True)) == names


def test_a_request_the_daemon_does_not_know_is_refused_by_name() -> None:
    request = decode_request(encode_line(ControlRun(session_id=4, command="pause", user_id=2, credential="login")))
    assert request == ControlRun(session_id=4, command="pause", user_id=2, credential="login")
    with pytest.raises(msgspec.ValidationError, match="Invalid value 'jump'"):
        decode_request(b'{"cmd": "jump"}')
    with pytest.raises(msgspec.ValidationError, match=r"\$\.command"):
        decode_request(b'{"cmd": "control", "session_id": 4, "command": "go", "user_id": 2, "credential": "x"}')
    with pytest.raises(msgspec.ValidationError, match=r"\$\.session_id"):
        decode_request(b'{"cmd": "start", "session_id": "four", "user_id": 2}')
