"""Checks a prescription before it is stored: finite numbers, a valid cue spec and washout parameter set per
segment (validated by `core.cues.validate_cue_spec` and `core.washout.WashoutParameters.from_dict`), and
per-prescription limits that may only tighten the robot's own `MotionLimits`. Refusals name the field."""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

from core import cues, washout
from core.robot import TwinRobot
from server.errors import InvalidFieldError


def robot_limits(twin: TwinRobot) -> dict[str, float]:
    return {name: float(value) for name, value in asdict(twin.robot.limits).items()}


def _require_finite(field: str, value: Any) -> None:
    if isinstance(value, bool):
        return
    if isinstance(value, float) and not math.isfinite(value):
        raise InvalidFieldError(field, value, "must be a finite number")
    if isinstance(value, dict):
        for key, item in value.items():
            _require_finite(f"{field}.{key}", item)
    elif isinstance(value, list):
        for index, item in enumerate(value):
            _require_finite(f"{field}[{index}]", item)


def _refusal(field: str, value: Any, error: Exception) -> InvalidFieldError:
    """Carry the core validator's own field/value/limit over, prefixed with where it sits in the prescription."""
    inner_field = getattr(error, "field", None)
    return InvalidFieldError(
        f"{field}.{inner_field}" if inner_field else field,
        getattr(error, "value", value),
        str(getattr(error, "limit", None) or error),
    )


CSV_CUE_MAX_BYTES = 32 * 1024 * 1024  # a csv_replay cue's text; parsing it is bounded before it starts


def _validated_cue(field: str, cue: dict[str, Any]) -> dict[str, Any]:
    text = cue.get("csv") if isinstance(cue, dict) else None
    if isinstance(text, str) and len(text) > CSV_CUE_MAX_BYTES:
        raise InvalidFieldError(f"{field}.csv", f"{len(text)} characters", f"must be at most {CSV_CUE_MAX_BYTES} bytes")
    try:
        cues.validate_cue_spec(cue)
    except Exception as error:  # any refusal by the core validator is bad input here
        raise _refusal(field, cue, error) from error
    return cue


def _validated_washout(field: str, parameter_set: dict[str, Any] | None) -> dict[str, Any]:
    try:
        # Without an explicit set, the parameter set that reproduces paper Section 5 is used.
        parameters = (
            washout.paper_tilt_parameters()
            if parameter_set is None
            else washout.WashoutParameters.from_dict(parameter_set)
        )
    except Exception as error:
        raise _refusal(field, parameter_set, error) from error
    normalised: dict[str, Any] = parameters.to_dict()
    return normalised


def _validated_limits(field: str, limits: dict[str, float], robot: dict[str, float]) -> dict[str, float]:
    for name, value in limits.items():
        if name not in robot:
            raise InvalidFieldError(f"{field}.{name}", value, f"unknown limit; known: {sorted(robot)}")
        if not 0.0 < value <= robot[name]:
            raise InvalidFieldError(
                f"{field}.{name}", value, f"must be > 0 and <= the robot's own limit {robot[name]:g} (only tighten)"
            )
    return dict(limits)


def validated_prescription(
    segments: list[dict[str, Any]], *, limits: dict[str, float], cueing: str = "classical"
) -> dict[str, Any]:
    """The prescription as stored and run: `{"segments": [{cue, duration_s, washout, limits}, ...], "cueing"}`."""
    checked = []
    for index, segment in enumerate(segments):
        field = f"segments[{index}]"
        _require_finite(field, segment)
        checked.append(
            {
                "cue": _validated_cue(f"{field}.cue", segment["cue"]),
                "duration_s": float(segment["duration_s"]),
                "washout": _validated_washout(f"{field}.washout", segment.get("washout")),
                "limits": _validated_limits(f"{field}.limits", segment.get("limits") or {}, limits),
            }
        )
    return {"segments": checked, "cueing": cueing}
