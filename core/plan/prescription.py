"""The prescription, as one pydantic model: what the API, the preview, the CLI and the robot daemon accept.

    {"name"?, "segments": [{"cue": {"kind": ..., ...}, "duration_s", "washout"?, "shaping"?, "limits"?}],
     "cueing"?: "classical" | "optimal", "seed"?}

- `cue` is a union discriminated by `kind`, one model per kind of `core.cues`, every field with its type,
  range and unit; the rules between fields (an axis and the unit of its amplitude, a step's end after its
  start, ...) are `core.cues`' own and run as part of validation (a CSV's rows: when the plan is built).
- `washout` holds `core.washout.WashoutParameters` (default: the set that reproduces paper §5), `shaping`
  `core.shaping.ShapingParameters`, `limits` overrides of `core.robot.MotionLimits`.
- At most `SEGMENT_COUNT_MAX` segments, everywhere.

Refusals keep the path a clinician's screen reads (`segments[0].cue.amplitude_m_s2`: the union's tag is not
part of it) and the message names the field, the value and the limit. What depends on the robot (a limit may
only tighten the robot's own) or on the control rate is checked when the plan is built (`core.plan.build`),
with the same error shape (`PrescriptionError`).

`content()` is what is stored: the cue as given, washout and shaping in full, limits as given. A stored
content validates back to itself; versions stored before shaping existed load with the default shaping.
"""

from __future__ import annotations

import dataclasses
import math
import re
import typing
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, create_model, model_validator
from pydantic_core import InitErrorDetails, PydanticCustomError

from core import cues
from core.cues import CueSpecError
from core.errors import InvalidValueError
from core.plan.config import FADE_OUT_MAX_S, SEGMENT_DURATION_MAX_S
from core.robot import MotionLimits
from core.shaping import SHAPING_KINDS, ParameterError, ShapingParameters
from core.validation import StrictModel
from core.washout import HEAD_HEIGHT_MAX_M, WashoutParameters, paper_tilt_parameters

SEGMENT_COUNT_MAX = 100
CSV_CUE_MAX_BYTES = 32 * 1024 * 1024  # a csv_replay cue's text; parsing it is bounded before it starts
SEED_MAX = 2**32 - 1  # numpy's generators take non-negative seeds
CUEING_ALGORITHMS = ("classical", "optimal")
_SHOWN_CHARS = 80


class PrescriptionError(InvalidValueError):
    """A malformed prescription or patient; names the field, the value and the rule it broke."""


_Strict = StrictModel  # unknown fields, NaN, ±inf and subnormal numbers refused at their field


# --- Cue kinds (core.cues) ----------------------------------------------------------------------------

Axis = Literal["x", "y", "z", "roll", "pitch", "yaw"]
_F = cues.SPECIFIC_FORCE_MAX_M_S2
_W = cues.ANGULAR_VELOCITY_MAX_RAD_S
_T = cues.CUE_TIME_MAX_S
_AXIS = "Axis: x forward, y left, z up (translation, specific force) or roll, pitch, yaw (rotation, angular velocity)."
_AMPLITUDE_M_S2 = f"Amplitude in m/s² of specific force, for x, y or z; |value| ≤ {_F:g} m/s²."
_AMPLITUDE_RAD_S = f"Amplitude in rad/s of angular velocity, for roll, pitch or yaw; |value| ≤ {_W:g} rad/s."
SignedForce = Annotated[float, Field(ge=-_F, le=_F)]
SignedRate = Annotated[float, Field(ge=-_W, le=_W)]


def _field_errors(error: InvalidValueError) -> ValidationError:
    """A core validator's refusal (field, value, limit) as a pydantic error located at that field."""
    return ValidationError.from_exception_data(
        "cue",
        [
            InitErrorDetails(
                type=PydanticCustomError("value_error", "{limit}", {"limit": error.limit}),
                loc=_loc(error.field),
                input=error.value,
            )
        ],
    )


def _loc(path: str) -> tuple[str | int, ...]:
    """ "components[1].amplitude_m_s2" → ("components", 1, "amplitude_m_s2")."""
    return tuple(int(part) if part.isdigit() else part for part in re.findall(r"[^.\[\]]+", path))


class _Cue(_Strict):
    """A cue kind; `core.cues` builds its generator from `spec()` and checks the rules between fields."""

    kind: str
    # Checked when the plan is built (`core.plan.build.check_for_robot`), not by the model: the API validates
    # request bodies on its event loop, and parsing up to 32 MiB of CSV there would stall it.
    check_deferred: ClassVar[bool] = False

    def spec(self) -> dict[str, Any]:
        """The cue as given (defaults stay implicit, so a stored cue reads as it was written)."""
        return {"kind": self.kind} | self.model_dump(exclude_unset=True, exclude_none=True)

    @model_validator(mode="after")
    def _generator_accepts(self) -> _Cue:
        if not self.check_deferred:
            try:
                cues.validate_cue_spec(self.spec())
            except CueSpecError as error:
                raise _field_errors(error) from None
        return self


class _AxisCue(_Cue):
    axis: Axis = Field(description=_AXIS)
    amplitude_m_s2: SignedForce | None = Field(None, description=_AMPLITUDE_M_S2)
    amplitude_rad_s: SignedRate | None = Field(None, description=_AMPLITUDE_RAD_S)


class SquareWaveCue(_AxisCue):
    """±amplitude with the given period and duty cycle, from `start_s` (paper §4.2 tuning input)."""

    kind: Literal["square_wave"]
    period_s: float = Field(ge=2.0 / cues.FREQUENCY_MAX_HZ, le=_T, description="Period in s.")
    duty: float = Field(0.5, ge=0.05, le=0.95, description="Fraction of the period at +amplitude.")
    start_s: float = Field(0.0, ge=0.0, le=_T, description="Start in s (0 before it).")


class StepCue(_Cue):
    """`initial` until `step_time_s`, then `final`; back to `initial` at `end_time_s` if given (§3.2, §4.3).
    Translation axes take `initial_m_s2`/`final_m_s2`, rotation axes `initial_rad_s`/`final_rad_s`."""

    kind: Literal["step"]
    axis: Axis = Field(description=_AXIS)
    initial_m_s2: SignedForce | None = Field(
        None, description=f"Specific force before the step, m/s² (default 0); |value| ≤ {_F:g}."
    )
    final_m_s2: SignedForce | None = Field(None, description=f"Specific force after the step, m/s²; |value| ≤ {_F:g}.")
    initial_rad_s: SignedRate | None = Field(
        None, description=f"Angular velocity before the step, rad/s (default 0); |value| ≤ {_W:g}."
    )
    final_rad_s: SignedRate | None = Field(
        None, description=f"Angular velocity after the step, rad/s; |value| ≤ {_W:g}."
    )
    step_time_s: float = Field(0.0, ge=0.0, le=_T, description="Time of the step, s.")
    end_time_s: float | None = Field(
        None, ge=0.0, le=_T, description="Back to initial at this time, s (after step_time_s); default never."
    )


class SineComponent(_Strict):
    axis: Axis = Field(description=_AXIS)
    amplitude_m_s2: SignedForce | None = Field(None, description=_AMPLITUDE_M_S2)
    amplitude_rad_s: SignedRate | None = Field(None, description=_AMPLITUDE_RAD_S)
    frequency_hz: float = Field(
        gt=0.0, le=cues.FREQUENCY_MAX_HZ, description="Frequency in Hz (below the first mode, 9.76 Hz)."
    )
    phase_rad: float = Field(0.0, ge=-2.0 * math.pi, le=2.0 * math.pi, description="Phase in rad.")


class SineCue(_Cue, SineComponent):
    """amplitude · sin(2π f t + phase) on one axis."""

    kind: Literal["sine"]


class MultisineCue(_Cue):
    """A sum of sines, each on its own axis."""

    kind: Literal["multisine"]
    components: list[SineComponent] = Field(min_length=1, max_length=32, description="1 to 32 sine components.")


class GaitCue(_Cue):
    """Walking-like: vertical and fore-aft at the step frequency, lateral and roll at the stride frequency
    (half of it). At least one amplitude must be > 0."""

    kind: Literal["gait"]
    cadence_steps_per_min: float = Field(
        ge=cues.CADENCE_RANGE_STEPS_PER_MIN[0], le=cues.CADENCE_RANGE_STEPS_PER_MIN[1], description="Steps per minute."
    )
    vertical_amplitude_m_s2: float = Field(0.0, ge=0.0, le=_F, description="Vertical specific force, m/s².")
    forward_amplitude_m_s2: float = Field(0.0, ge=0.0, le=_F, description="Fore-aft specific force, m/s².")
    lateral_amplitude_m_s2: float = Field(0.0, ge=0.0, le=_F, description="Lateral specific force, m/s².")
    roll_amplitude_rad_s: float = Field(0.0, ge=0.0, le=_W, description="Roll rate, rad/s.")


class PerturbationsCue(_Cue):
    """Seeded random pulses (one sine period each) in a random horizontal direction: translation and/or
    tilt. The prescription's seed plus the segment index seeds them."""

    kind: Literal["perturbations"]
    translation_m_s2: float = Field(0.0, ge=0.0, le=_F, description="Peak specific force of a translation pulse, m/s².")
    tilt_rate_rad_s: float = Field(0.0, ge=0.0, le=_W, description="Peak angular velocity of a tilt pulse, rad/s.")
    pulse_duration_s: float = Field(0.5, ge=1.0 / cues.FREQUENCY_MAX_HZ, le=10.0, description="Pulse length, s.")
    interval_min_s: float | None = Field(
        None, le=_T, description="Shortest gap between onsets, s (≥ the pulse; default max(pulse, 3 s))."
    )
    interval_max_s: float | None = Field(
        None, le=_T, description="Longest gap between onsets, s (≥ interval_min_s; default max(interval_min_s, 8 s))."
    )
    first_onset_s: float | None = Field(None, ge=0.0, le=_T, description="First pulse, s (default interval_min_s).")


class CsvReplayCue(_Cue):
    """Replay of recorded samples, linearly interpolated onto the control period; zero after the last row."""

    kind: Literal["csv_replay"]
    check_deferred: ClassVar[bool] = True  # the CSV is parsed in the request's worker thread
    csv: str = Field(
        max_length=CSV_CUE_MAX_BYTES,
        description="CSV text with a header: time_s, specific_force_x_m_s2, specific_force_y_m_s2, "
        "specific_force_z_m_s2 and optionally angular_velocity_x_rad_s, _y_, _z_ (s, m/s², rad/s).",
    )


Cue = Annotated[
    SquareWaveCue | StepCue | SineCue | MultisineCue | GaitCue | PerturbationsCue | CsvReplayCue,
    Field(discriminator="kind", description="What the patient should feel (core.cues), chosen by `kind`."),
]
_CUE_MODELS = typing.get_args(typing.get_args(Cue)[0])
if sorted(typing.get_args(m.model_fields["kind"].annotation)[0] for m in _CUE_MODELS) != sorted(cues.CUE_KINDS):
    raise ImportError("core.plan.prescription: the cue union must hold every kind core.cues supports")


# --- Parameter blocks generated from the core dataclasses (one set of defaults) --------------------------


class _ParameterBlock(_Strict):
    """A parameter set of a core dataclass: the model checks each field, the dataclass the rules between them."""

    def parameters(self) -> Any:
        raise NotImplementedError

    @model_validator(mode="after")
    def _consistent(self) -> _ParameterBlock:
        try:
            self.parameters()
        except ParameterError as error:
            raise _field_errors(error) from None
        return self


def _parameters_model(
    cls: type, descriptions: Mapping[str, str], bounds: Mapping[str, dict[str, Any]]
) -> type[BaseModel]:
    """The fields of the dataclass `cls`, typed and bounded, with its defaults (one set of them)."""
    hints = typing.get_type_hints(cls)
    defaults = cls()
    fields: dict[str, Any] = {}
    for item in dataclasses.fields(cls):
        kind = hints[item.name]
        kind = Literal[SHAPING_KINDS] if item.name == "kind" else kind
        fields[item.name] = (
            kind,
            Field(getattr(defaults, item.name), description=descriptions[item.name], **bounds.get(item.name, {})),
        )
    model: type[BaseModel] = create_model(f"_{cls.__name__}Fields", __base__=_ParameterBlock, **fields)
    return model


_WASHOUT_DESCRIPTIONS = {
    "specific_force_gain": "Scale of the specific-force cue (0 switches the channel off).",
    "specific_force_limit_m_s2": "Limit of the scaled specific force, m/s².",
    "translational_damping": "ξ of the translational high-pass (Formula 12).",
    "translational_break_rad_s": "ω_a of the translational high-pass, rad/s.",
    "translational_first_order_break_rad_s": "ω_a′, the first-order break of the translational high-pass, rad/s.",
    "tilt_damping": "ξ of the tilt-coordination low-pass (Formula 13).",
    "tilt_break_rad_s": "ω_h of the tilt-coordination low-pass, rad/s.",
    "tilt_rate_limit_rad_s": "Largest tilt-coordination rate, rad/s (perception threshold).",
    "angular_velocity_gain": "Scale of the angular-velocity cue (0 switches the channel off).",
    "angular_velocity_limit_rad_s": "Limit of the scaled angular velocity, rad/s.",
    "rotational_damping": "ξ of the rotational high-pass.",
    "rotational_break_rad_s": "Break of the rotational high-pass, rad/s.",
    "head_height_m": f"Head above the foot plates, m, in [0, {HEAD_HEIGHT_MAX_M:g}]; 0: cue at the rotation centre.",
}
# Physical ranges: far wider than any tuning uses, narrow enough that every filter design stays well conditioned.
GAIN_MAX = 10.0
BREAK_RANGE_RAD_S = (0.001, 100.0)  # the tuner searches down to 0.001 rad/s (core.tuning.DEFAULT_BOUNDS)
DAMPING_RANGE = (0.05, 10.0)


def _washout_bounds(name: str) -> dict[str, float]:
    if name.endswith("_gain"):
        return {"ge": 0.0, "le": GAIN_MAX}
    if name.endswith("_break_rad_s"):
        return {"ge": BREAK_RANGE_RAD_S[0], "le": BREAK_RANGE_RAD_S[1]}
    if name.endswith("_damping"):
        return {"ge": DAMPING_RANGE[0], "le": DAMPING_RANGE[1]}
    if name == "specific_force_limit_m_s2":
        return {"gt": 0.0, "le": _F}
    if name.endswith("_limit_rad_s"):
        return {"gt": 0.0, "le": _W}
    return {"ge": 0.0, "le": HEAD_HEIGHT_MAX_M}  # head_height_m


_WASHOUT_BOUNDS = {name: _washout_bounds(name) for name in _WASHOUT_DESCRIPTIONS}
_WashoutFields = _parameters_model(WashoutParameters, _WASHOUT_DESCRIPTIONS, _WASHOUT_BOUNDS)


class Washout(_WashoutFields):  # type: ignore[misc, valid-type]
    """Classical washout (paper §4.1, `core.washout.WashoutParameters`), SI units. Left out: the set that
    reproduces paper §5; a field left out of a given block takes the baseline value shown."""

    def parameters(self) -> WashoutParameters:
        return WashoutParameters.from_dict(self.model_dump())


_SHAPING_DESCRIPTIONS = {
    "enabled": "Shape the platform commands against the first natural frequency.",
    "kind": "lowpass (Butterworth) or notch.",
    "lowpass_cutoff_hz": "Low-pass cut-off, Hz.",
    "lowpass_order": "Low-pass order, 1 to 8.",
    "notch_frequency_hz": "Notch centre, Hz.",
    "notch_quality": "Notch quality: centre over −3 dB bandwidth.",
    "first_mode_hz": "First natural frequency to keep out, Hz (paper §3.3.2).",
    "mode_band_fraction": "Half-width of the band around the mode, as a fraction of it, in [0, 1).",
    "required_attenuation_db": "Attenuation required over that band, dB.",
}
SHAPING_FREQUENCY_RANGE_HZ = (0.1, 100.0)  # cut-offs, notches and modes; the control rate's Nyquist is 500 Hz
_SHAPING_BOUNDS: dict[str, dict[str, Any]] = {
    "lowpass_cutoff_hz": {"ge": SHAPING_FREQUENCY_RANGE_HZ[0], "le": SHAPING_FREQUENCY_RANGE_HZ[1]},
    "lowpass_order": {"ge": 1, "le": 8},
    "notch_frequency_hz": {"ge": SHAPING_FREQUENCY_RANGE_HZ[0], "le": SHAPING_FREQUENCY_RANGE_HZ[1]},
    "notch_quality": {"ge": 0.05, "le": 100.0},
    "first_mode_hz": {"ge": SHAPING_FREQUENCY_RANGE_HZ[0], "le": SHAPING_FREQUENCY_RANGE_HZ[1]},
    "mode_band_fraction": {"ge": 0.0, "lt": 1.0},
    "required_attenuation_db": {"ge": 0.0, "le": 120.0},
}
_ShapingFields = _parameters_model(ShapingParameters, _SHAPING_DESCRIPTIONS, _SHAPING_BOUNDS)


class Shaping(_ShapingFields):  # type: ignore[misc, valid-type]
    """Command shaping of every pose coordinate against the first natural frequency (`core.shaping`).
    A field left out takes the default shown."""

    def parameters(self) -> ShapingParameters:
        return ShapingParameters.from_dict(self.model_dump())


_LIMIT_DESCRIPTIONS = {
    "slider_velocity_max_m_s": "Largest slider speed, m/s.",
    "slider_acceleration_max_m_s2": "Largest slider acceleration, m/s².",
    "drive_force_max_n": "Largest predicted drive force, N.",
    "tilt_max_rad": "Largest platform tilt, rad.",
    "base_joint_cone_rad": "Half-angle of each base spherical joint's cone, rad.",
    "platform_joint_cone_rad": "Half-angle of each platform spherical joint's cone, rad.",
    "condition_number_max": "Largest condition number of the twist Jacobian (distance from singularities).",
}
_LimitFields: type[BaseModel] = create_model(
    "_MotionLimitFields",
    __base__=_Strict,
    **{
        item.name: (float | None, Field(None, gt=0.0, description=_LIMIT_DESCRIPTIONS[item.name]))
        for item in dataclasses.fields(MotionLimits)
    },  # type: ignore[call-overload]
)


class Limits(_LimitFields):  # type: ignore[misc, valid-type]
    """Overrides of the robot's `MotionLimits` for one segment; each may only tighten the robot's own."""

    def overrides(self) -> dict[str, float]:
        """The limits given (the others stay the robot's)."""
        return {name: value for name, value in self.model_dump().items() if value is not None}


# --- Segments and the prescription ---------------------------------------------------------------------


class Segment(_Strict):
    cue: Cue
    duration_s: float = Field(
        gt=0.0,
        le=SEGMENT_DURATION_MAX_S,
        description=f"Duration of the cue, s: at least the soft start, at most {SEGMENT_DURATION_MAX_S:g} s (the cue "
        f"generator's {cues.CUE_TIME_MAX_S:g} s hold the fade out that follows too, up to {FADE_OUT_MAX_S:g} s).",
    )
    washout: Washout = Field(
        default_factory=lambda: Washout(**paper_tilt_parameters().to_dict()),
        description="Classical washout; default: the set that reproduces paper Section 5.",
    )
    shaping: Shaping = Field(default_factory=Shaping, description="Command shaping against the first mode.")
    limits: Limits = Field(default_factory=Limits, description="Limit overrides; they may only tighten the robot's.")

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.5},
                    "duration_s": 60.0,
                    "limits": {"tilt_max_rad": 0.2},
                }
            ]
        }
    )

    def content(self) -> dict[str, Any]:
        return {
            "cue": self.cue.spec(),
            "duration_s": self.duration_s,
            "washout": self.washout.model_dump(),
            "shaping": self.shaping.model_dump(),
            "limits": self.limit_overrides(),
        }

    def limit_overrides(self) -> dict[str, float]:
        return self.limits.overrides()


class PrescriptionBody(_Strict):
    """What is prescribed; the API's request bodies add their own fields (patient, note) to it."""

    segments: list[Segment] = Field(
        min_length=1, max_length=SEGMENT_COUNT_MAX, description=f"1 to {SEGMENT_COUNT_MAX} segments, played in order."
    )
    cueing: Literal["classical", "optimal"] = Field(
        "classical",
        description="Motion cueing: the paper's classical washout, or optimal cueing planned over the whole "
        "prescription (core.optimal_cueing).",
    )
    seed: int = Field(0, ge=0, le=SEED_MAX, description="Seeds the random cues (segment i uses seed + i).")

    @model_validator(mode="wrap")
    @classmethod
    def _located(cls, data: Any, handler: Any) -> Any:
        """Refusals at the path the screen knows, naming the value and the limit."""
        try:
            return handler(data)
        except ValidationError as error:
            raise ValidationError.from_exception_data(error.title, [_located(e) for e in error.errors()]) from None

    def content(self) -> dict[str, Any]:
        """The prescription as stored and run."""
        return {"segments": [s.content() for s in self.segments], "cueing": self.cueing, "seed": self.seed}


class Prescription(PrescriptionBody):
    """A prescription with its name: the body of `POST /api/v1/prescriptions` less the patient and the note."""

    name: str | None = Field(None, max_length=200, description="Name shown to clinicians.")


def _located(error: Mapping[str, Any]) -> InitErrorDetails:
    loc = tuple(error["loc"])
    # A discriminated union puts its tag into the path (segments.0.cue.sine.frequency_hz): drop it.
    loc = tuple(part for i, part in enumerate(loc) if not (i and loc[i - 1] == "cue" and part in cues.CUE_KINDS))
    path = error_path(loc)
    ctx = dict(error.get("ctx") or {})
    reason = str(ctx.get("limit") or error["msg"])
    if error["type"] == "missing":  # the input is the object the field is missing from: not worth showing
        message = f"{path}: required"
    else:
        message = f"{path} = {_shown(error.get('input'))}: {reason}" if path else reason
    return InitErrorDetails(
        type=PydanticCustomError(error["type"], message, ctx | {"limit": reason}),
        loc=loc,
        input=error.get("input"),
    )


def error_path(loc: tuple[Any, ...]) -> str:
    """("segments", 0, "cue", "x") → "segments[0].cue.x", as refusals and the console name fields."""
    path = ""
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else (f".{part}" if path else str(part))
    return path


def _shown(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= _SHOWN_CHARS else text[: _SHOWN_CHARS - 1] + "…"


def parse_prescription(data: Any) -> Prescription:
    """Validate a prescription that does not come through the API (CLI file, stored content, worker command);
    refuses with `PrescriptionError` at the first invalid field."""
    if isinstance(data, PrescriptionBody):
        return data if isinstance(data, Prescription) else Prescription.model_validate(data.content())
    if not isinstance(data, Mapping):
        raise PrescriptionError("prescription", _shown(data), "must be an object with 'segments'")
    try:
        return Prescription.model_validate(dict(data))
    except ValidationError as error:
        first = error.errors()[0]
        path = error_path(tuple(first["loc"])) or "prescription"
        value = None if first["type"] == "missing" else first.get("input")
        value = value if value is None or isinstance(value, bool | int | float) else _shown(value)
        limit = "required" if first["type"] == "missing" else str((first.get("ctx") or {}).get("limit") or first["msg"])
        raise PrescriptionError(path, value, limit) from None
