"""A simulated patient standing on the twin platforms (issue 8; REFERENCE.md §5; paper §1).

The body is an inverted pendulum about the ankles in the sagittal (AP) plane and about the point
between the feet in the frontal (ML) plane, on a moving support: the support's acceleration and tilt
enter the equations of motion,

    I·θ̈ = m·h·((g + a_z)·sin θ − a_x·cos θ) − τ_ankle + M_harness        (AP; ML alike with a_y)

Balance is Peterka's (2002, J Neurophysiol 88:1097) independent-channel model: a delayed PD on a
sensed angle that mixes proprioception (relative to the tilting foot) and graviceptive cues, plus
passive ankle stiffness and damping, with seeded sensory and motor noise. The torque saturates at
the ankle's strength and where the centre of pressure reaches the edge of the feet. A chest harness
on a rope (slack, stiffness, damping) from an anchor above catches a fall, so its load rises.

Body sizes are from Winter (2009), *Biomechanics and Motor Control of Human Movement*, 4th ed.,
Table 4.1 and Fig. 4.1: COM height 0.55·H (NeuroCom uses 0.5527·H), ankle height 0.039·H, foot length
0.152·H, foot breadth 0.055·H, two feet 2 × 0.0145 of the body mass; whole-body radius of gyration
about the COM 0.24·H (Santschi, Dubois & Omoto 1963, AMRL-TDR-63-36).

Frames: x anterior, y to the patient's left, z up. Per-foot readings are ordered (right, left); each
foot-plate frame has its origin under that ankle. Ground truth: the patient has fallen once the COM's
ground projection leaves the base of support (they must then step, grab or be caught, which clinical
protocols count as a fall) or once they lean far enough to take up the harness slack (they are being
caught); `fall_onset_s` is the first such instant. Both are kinematic, independent of any sensor.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numba
import numpy as np

from core.errors import InvalidValueError

GRAVITY_M_S2 = 9.80665
MAX_INTERNAL_STEP_S = 0.001  # the rope is stiff: integrate at ≤ 1 ms whatever the caller's period
FLOOR_ANGLE_RAD = 1.2  # the body lies against the frame/floor beyond this lean

# Anthropometry (Winter 2009, Table 4.1 / Fig. 4.1; Santschi et al. 1963), fractions of height or mass.
COM_HEIGHT_FRACTION = 0.55
ANKLE_HEIGHT_FRACTION = 0.039
FOOT_LENGTH_FRACTION = 0.152
FOOT_BREADTH_FRACTION = 0.055
FEET_MASS_FRACTION = 2 * 0.0145
RADIUS_OF_GYRATION_FRACTION = 0.24
# Where the ankle sits along the foot, from the heel (assumption: Winter gives no single figure).
ANKLE_FROM_HEEL_FRACTION = 0.25


class ParameterError(InvalidValueError):
    """An invalid parameter; names the field, the value and the limit it broke."""


def require_in_range(
    field_name: str, value: float, low: float, high: float, *, low_open: bool = False, high_open: bool = False
) -> None:
    """Refuse a non-finite `value` or one outside [low, high] (bounds optionally open)."""
    number = float(value)
    below = number <= low if low_open else number < low
    above = number >= high if high_open else number > high
    if not math.isfinite(number) or below or above:
        left, right = "(" if low_open else "[", ")" if high_open else "]"
        raise ParameterError(field_name, value, f"must be a finite number in {left}{low:g}, {high:g}{right}")


@dataclass(frozen=True)
class FootGeometry:
    """One foot's footprint in its foot-plate frame (origin under the ankle), metres."""

    heel_m: float  # behind the ankle (positive number)
    toe_m: float  # ahead of the ankle
    half_breadth_m: float

    @classmethod
    def from_height(cls, height_m: float) -> FootGeometry:
        length = FOOT_LENGTH_FRACTION * height_m
        return cls(
            heel_m=ANKLE_FROM_HEEL_FRACTION * length,
            toe_m=(1.0 - ANKLE_FROM_HEEL_FRACTION) * length,
            half_breadth_m=0.5 * FOOT_BREADTH_FRACTION * height_m,
        )


@dataclass(frozen=True)
class PatientParameters:
    """Body size, balance control and harness. Gains are normalised by m·g·h (h: COM above the ankle).

    Build one with `PatientParameters.preset("healthy" | "impaired", body_mass_kg, height_m)` and adjust
    with `dataclasses.replace`; every field is validated on construction.
    """

    body_mass_kg: float
    height_m: float
    preset_name: str = "custom"
    # Peterka (2002) fits for quiet stance: Kp ≈ 1.2–1.6·mgh, Kd ≈ 0.3–0.4·mgh·s, delay ≈ 0.15–0.2 s.
    feedback_delay_s: float = 0.15
    proportional_gain_per_mgh: float = 1.5  # N·m/rad ÷ (m·g·h)
    derivative_gain_per_mgh_s: float = 0.35  # N·m·s/rad ÷ (m·g·h)
    passive_stiffness_per_mgh: float = 0.15
    passive_damping_per_mgh_s: float = 0.03
    proprioceptive_weight: float = 0.2  # share of the sensed angle taken relative to the (tilting) foot
    sensory_noise_rad: float = 0.002  # std of the low-pass sensed-angle noise
    sensory_noise_time_constant_s: float = 0.5
    motor_noise_per_mgh: float = 0.004  # std of the low-pass torque noise ÷ (m·g·h)
    motor_noise_time_constant_s: float = 0.1
    ankle_torque_max_n_m_per_kg: float = 2.0
    stance_width_m: float = 0.5  # ankle to ankle; the default twin puts the foot plates 0.5 m apart
    harness_attachment_height_fraction: float = 0.72  # chest harness, fraction of height above the floor
    harness_anchor_above_attachment_m: float = 1.0
    harness_slack_m: float = 0.05
    harness_stiffness_n_m: float = 10_000.0
    harness_damping_n_s_m: float = 1000.0  # a shock-absorbing lanyard
    # The support's sensed acceleration drives a share of the torque that cancels its inertial push m·h·a
    # (the automatic postural response; feedback alone resonates near 0.3-0.5 Hz, where training cues sit).
    # Training cues are predictable, so the feedforward is predictive (no delay; Dietz et al. 1993, Exp
    # Brain Res 93:352, on stance on a sinusoidally translating platform).
    acceleration_feedforward_gain: float = 1.0
    acceleration_feedforward_delay_s: float = 0.0
    # The feedforward torque is made by muscles: activation dynamics, a critically damped second-order
    # low-pass at 16.8 rad/s (Mugge et al. 2010, relative damping 0.99; used by Pasma et al. 2017), whose lag
    # the anticipation of a predictable cue makes up. Without it the torque followed the support's
    # acceleration up to any frequency: on the MuJoCo backend a 120 kg patient rang with the structure at 89 Hz.
    muscle_activation_frequency_hz: float = 2.67
    hip_torque_max_n_m_per_kg: float = 0.5  # the hip strategy's moment (Horak & Nashner 1986); size ours
    # Once the extrapolated COM leaves the feet: a step, a grab of the rail, or neither (the harness
    # catches); the shares and times are ours, after Maki & McIlroy (1997).
    step_probability: float = 0.6
    grab_probability: float = 0.3
    protective_reaction_s: float = 0.25
    step_swing_s: float = 0.35
    grab_load_fraction_bw: float = 0.3
    leg_buckle_fraction: float = 0.6
    plate_force_noise_n: float = 2.0
    plate_cop_noise_m: float = 0.001
    harness_load_noise_n: float = 2.0

    def __post_init__(self) -> None:
        self._validate()

    @classmethod
    def preset(cls, name: str, body_mass_kg: float, height_m: float, **overrides: Any) -> PatientParameters:
        """ "healthy": Peterka's (2002) young-adult fit. "impaired": longer delay, a lower stiffness, more
        noise, weaker ankles, weaker hips and more reliance on the surface (proprioception weighted up), so
        that it copes with quiet stance and training sines but not with large perturbations. Its damping
        rises with its delay so that its closed loop keeps a margin like a person's (docs/falls.md)."""
        if name not in PRESETS:
            raise ParameterError("preset", name, f"must be one of {sorted(PRESETS)}")
        return cls(body_mass_kg=body_mass_kg, height_m=height_m, preset_name=name, **{**PRESETS[name], **overrides})

    def _validate(self) -> None:
        require_in_range("body_mass_kg", self.body_mass_kg, 20.0, 250.0)
        require_in_range("height_m", self.height_m, 1.0, 2.3)
        require_in_range("feedback_delay_s", self.feedback_delay_s, 0.0, 0.5)
        require_in_range("proportional_gain_per_mgh", self.proportional_gain_per_mgh, 0.0, 10.0)
        require_in_range("derivative_gain_per_mgh_s", self.derivative_gain_per_mgh_s, 0.0, 5.0)
        require_in_range("passive_stiffness_per_mgh", self.passive_stiffness_per_mgh, 0.0, 5.0)
        require_in_range("passive_damping_per_mgh_s", self.passive_damping_per_mgh_s, 0.0, 5.0)
        require_in_range("proprioceptive_weight", self.proprioceptive_weight, 0.0, 1.0)
        require_in_range("sensory_noise_rad", self.sensory_noise_rad, 0.0, 0.1)
        require_in_range("sensory_noise_time_constant_s", self.sensory_noise_time_constant_s, 0.0, 100.0, low_open=True)
        require_in_range("motor_noise_per_mgh", self.motor_noise_per_mgh, 0.0, 0.5)
        require_in_range("motor_noise_time_constant_s", self.motor_noise_time_constant_s, 0.0, 100.0, low_open=True)
        require_in_range("ankle_torque_max_n_m_per_kg", self.ankle_torque_max_n_m_per_kg, 0.0, 10.0, low_open=True)
        require_in_range("stance_width_m", self.stance_width_m, 0.05, 1.0)
        require_in_range("harness_attachment_height_fraction", self.harness_attachment_height_fraction, 0.3, 0.95)
        require_in_range("harness_anchor_above_attachment_m", self.harness_anchor_above_attachment_m, 0.1, 5.0)
        require_in_range("harness_slack_m", self.harness_slack_m, 0.0, 1.0)
        require_in_range("harness_stiffness_n_m", self.harness_stiffness_n_m, 100.0, 1e6)
        require_in_range("harness_damping_n_s_m", self.harness_damping_n_s_m, 0.0, 1e5)
        require_in_range("acceleration_feedforward_gain", self.acceleration_feedforward_gain, 0.0, 1.5)
        require_in_range("acceleration_feedforward_delay_s", self.acceleration_feedforward_delay_s, 0.0, 0.5)
        require_in_range("muscle_activation_frequency_hz", self.muscle_activation_frequency_hz, 0.5, 50.0)
        require_in_range("hip_torque_max_n_m_per_kg", self.hip_torque_max_n_m_per_kg, 0.0, 5.0)
        require_in_range("step_probability", self.step_probability, 0.0, 1.0)
        require_in_range("grab_probability", self.grab_probability, 0.0, 1.0 - self.step_probability)
        require_in_range("protective_reaction_s", self.protective_reaction_s, 0.0, 2.0)
        require_in_range("step_swing_s", self.step_swing_s, 0.05, 2.0)
        require_in_range("grab_load_fraction_bw", self.grab_load_fraction_bw, 0.0, 1.0)
        require_in_range("leg_buckle_fraction", self.leg_buckle_fraction, 0.0, 1.0)
        require_in_range("plate_force_noise_n", self.plate_force_noise_n, 0.0, 100.0)
        require_in_range("plate_cop_noise_m", self.plate_cop_noise_m, 0.0, 0.05)
        require_in_range("harness_load_noise_n", self.harness_load_noise_n, 0.0, 100.0)

    # --- derived body ------------------------------------------------------------------------------

    @property
    def body_weight_n(self) -> float:
        return self.body_mass_kg * GRAVITY_M_S2

    @property
    def pendulum_mass_kg(self) -> float:
        """Everything above the ankles."""
        return self.body_mass_kg * (1.0 - FEET_MASS_FRACTION)

    @property
    def com_height_above_ankle_m(self) -> float:
        return (COM_HEIGHT_FRACTION - ANKLE_HEIGHT_FRACTION) * self.height_m

    @property
    def moment_of_inertia_kg_m2(self) -> float:
        """About the ankle axis: m·(h² + k²), k the radius of gyration about the COM."""
        gyration = RADIUS_OF_GYRATION_FRACTION * self.height_m
        return self.pendulum_mass_kg * (self.com_height_above_ankle_m**2 + gyration**2)

    @property
    def gravity_stiffness_n_m(self) -> float:
        """m·g·h: the toppling stiffness the gains are normalised by."""
        return self.pendulum_mass_kg * GRAVITY_M_S2 * self.com_height_above_ankle_m

    @property
    def foot(self) -> FootGeometry:
        return FootGeometry.from_height(self.height_m)

    @property
    def harness_attachment_above_ankle_m(self) -> float:
        return (self.harness_attachment_height_fraction - ANKLE_HEIGHT_FRACTION) * self.height_m

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PatientParameters:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ParameterError(unknown[0], data[unknown[0]], "unknown patient parameter")
        return cls(**data)


PRESETS: dict[str, dict[str, float]] = {
    "healthy": {},
    # Gains within the identified ranges of healthy adults (Kp 1.33–1.55·mgh, Kd 0.51–0.87·mgh·s: Pasma et
    # al. 2017 JNER 14:97 Table 3; Engelhart/Pasma-group model, PMC5664365 Table 1) and passive stiffness at
    # Loram et al.'s (2007, J Physiol 584:661) long-range 13 % of mgh. The former preset (Kp 1.2, Kd 0.3,
    # passive 0.1, W 0.6) had a closed-loop resonance at 0.31 Hz (sway/tilt gain 6.3, sensitivity peak 7):
    # the washout's ±1.2° pitch of a 0.03 g, 0.25 Hz training sine toppled it (issue 16 §11).
    "impaired": {
        "feedback_delay_s": 0.2,
        "proportional_gain_per_mgh": 1.3,
        "derivative_gain_per_mgh_s": 0.5,
        "passive_stiffness_per_mgh": 0.13,
        "proprioceptive_weight": 0.5,
        "sensory_noise_rad": 0.003,
        "motor_noise_per_mgh": 0.006,
        "ankle_torque_max_n_m_per_kg": 1.2,
        "acceleration_feedforward_gain": 0.7,
        "hip_torque_max_n_m_per_kg": 0.25,
        "step_probability": 0.3,
        "grab_probability": 0.3,
        "protective_reaction_s": 0.35,
    },
}


# --- the per-step kernel (numba): one layout for the streaming and the batch front ends -------------

# parameter vector
(
    P_MASS,
    P_FEET_MASS,
    P_COM_HEIGHT,
    P_INERTIA,
    P_HEEL,
    P_TOE,
    P_HALF_BREADTH,
    P_HALF_WIDTH,
    P_ATTACH_HEIGHT,
    P_ANCHOR_HEIGHT,
    P_ROPE_REST,
    P_ROPE_K,
    P_ROPE_C,
    P_KP,
    P_KD,
    P_KPAS,
    P_BPAS,
    P_WPROP,
    P_TORQUE_MAX,
    P_SENSORY_DECAY,
    P_SENSORY_DRIVE,
    P_MOTOR_DECAY,
    P_MOTOR_DRIVE,
    P_FORCE_NOISE,
    P_COP_NOISE,
    P_HARNESS_NOISE,
    P_DT,
    P_SUBSTEPS,
    P_LEAK_RATE,
    P_FF_GAIN,
    P_FF_STEPS,
    P_FB_STEPS,
    P_OMEGA0,
    P_STEP_P,
    P_GRAB_P,
    P_REACTION,
    P_SWING,
    P_GRAB_LOAD,
    P_BUCKLE,
    P_RESCUE_K,
    P_RESCUE_C,
    P_HIP_MAX,
    P_ACTIVATION_OMEGA,
    P_SIZE,
) = range(44)

# state vector
(
    S_THETA_AP,
    S_OMEGA_AP,
    S_THETA_ML,
    S_OMEGA_ML,
    S_ACCEL_AP,
    S_ACCEL_ML,
    S_SUPPORT_X,
    S_SUPPORT_Y,
    S_SUPPORT_Z,
    S_SUPPORT_VX,
    S_SUPPORT_VY,
    S_SUPPORT_VZ,
    S_SENSORY_NOISE_AP,
    S_SENSORY_NOISE_ML,
    S_MOTOR_NOISE_AP,
    S_MOTOR_NOISE_ML,
    S_TIME,
    S_FALLEN,
    S_FALL_ONSET,
    S_DELAY_INDEX,
    S_FF_INDEX,
    S_RESPONSE,  # RESPONSE_* once balance is lost
    S_RESPONSE_TIME,  # since the loss of balance
    S_STEP_FOOT,  # 0 right, 1 left
    S_DROP,  # vertical sag of the body (m, down positive) when the legs give way
    S_DROP_RATE,
    S_FF_TORQUE_AP,  # the feedforward's activation dynamics: two states per plane (canonical form)
    S_FF_TORQUE_RATE_AP,
    S_FF_TORQUE_ML,
    S_FF_TORQUE_RATE_ML,
    S_SIZE,
) = range(31)

# What the patient does once the extrapolated COM has left the base of support.
RESPONSE_NONE, RESPONSE_STEP, RESPONSE_GRAB, RESPONSE_CATCH = 0, 1, 2, 3
RESPONSE_NAMES = {RESPONSE_STEP: "step", RESPONSE_GRAB: "grab", RESPONSE_CATCH: "harness_catch"}
LIFT_OFF_S = 0.05  # a stepping foot unloads over this long
GRAB_RAMP_S = 0.2  # the hand takes up its share of the weight over this long
BUCKLE_RAMP_S = 0.3  # the legs give way over this long
MAX_DROP_M = 0.35  # knees fully flexed: the sag ends here
RESCUE_STIFFNESS_PER_MGH = 4.0  # a planted step or a held rail stops the toppling
RESCUE_DAMPING_PER_MGH_S = 1.0
FUNCTIONAL_BASE_FRACTION = 0.8  # of the ankle-to-heel and ankle-to-toe distances: where the hips take over

# output vector
(
    O_FZ_RIGHT,
    O_FZ_LEFT,
    O_COP_RIGHT_X,
    O_COP_RIGHT_Y,
    O_COP_LEFT_X,
    O_COP_LEFT_Y,
    O_HARNESS,
    O_SWAY_AP,
    O_SWAY_ML,
    O_FALLEN,
    O_FALL_ONSET,
    O_TIME,
    O_RESPONSE,
    O_DROP,
    O_SIZE,
) = range(15)


@numba.njit(cache=True)
def _next_uniform(rng_state: np.ndarray) -> float:
    """splitmix64 (Steele, Lea & Flood 2014): a per-instance stream, so patients never share noise."""
    rng_state[0] += np.uint64(0x9E3779B97F4A7C15)
    z = rng_state[0]
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return (float(z >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True)
def _next_gaussian(rng_state: np.ndarray) -> float:
    """Box–Muller, one value per call (the pair's second value is dropped for a stateless stream)."""
    u1 = _next_uniform(rng_state)
    u2 = _next_uniform(rng_state)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


@numba.njit(cache=True)
def _rope_tension(p: np.ndarray, s: np.ndarray, rope: np.ndarray) -> float:
    """Tension (N) and the unit vector from the attachment to the anchor into rope[0:3]."""
    height = p[P_ATTACH_HEIGHT]
    sin_ap, cos_ap = math.sin(s[S_THETA_AP]), math.cos(s[S_THETA_AP])
    sin_ml, cos_ml = math.sin(s[S_THETA_ML]), math.cos(s[S_THETA_ML])
    # The anchor is fixed in the room; the feet move with the support (displacement s[S_SUPPORT_*]).
    attach_x = height * sin_ap + s[S_SUPPORT_X]
    attach_y = height * sin_ml + s[S_SUPPORT_Y]
    attach_z = height * cos_ap * cos_ml + s[S_SUPPORT_Z] - s[S_DROP]
    to_anchor_x = -attach_x
    to_anchor_y = -attach_y
    to_anchor_z = height + p[P_ANCHOR_HEIGHT] - attach_z
    length = math.sqrt(to_anchor_x**2 + to_anchor_y**2 + to_anchor_z**2)
    rope[0] = to_anchor_x / length
    rope[1] = to_anchor_y / length
    rope[2] = to_anchor_z / length
    stretch = length - p[P_ROPE_REST]
    if stretch <= 0.0:
        return 0.0
    velocity_x = height * cos_ap * s[S_OMEGA_AP] + s[S_SUPPORT_VX]
    velocity_y = height * cos_ml * s[S_OMEGA_ML] + s[S_SUPPORT_VY]
    velocity_z = (
        -height * (sin_ap * cos_ml * s[S_OMEGA_AP] + cos_ap * sin_ml * s[S_OMEGA_ML]) + s[S_SUPPORT_VZ] - s[S_DROP_RATE]
    )
    lengthening_rate = -(rope[0] * velocity_x + rope[1] * velocity_y + rope[2] * velocity_z)
    return max(0.0, p[P_ROPE_K] * stretch + p[P_ROPE_C] * lengthening_rate)  # a rope only pulls


@numba.njit(cache=True)
def _clamp(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


@numba.njit(cache=True)
def _patient_step(
    p: np.ndarray,
    s: np.ndarray,
    delay: np.ndarray,
    rng_state: np.ndarray,
    rope: np.ndarray,
    acceleration: np.ndarray,
    tilt: np.ndarray,
    angular_velocity: np.ndarray,
    out: np.ndarray,
) -> None:
    dt = p[P_DT] / p[P_SUBSTEPS]
    mass, height, inertia = p[P_MASS], p[P_COM_HEIGHT], p[P_INERTIA]
    # Plate normal direction as a lean angle in each plane: pitch tips the toes down (+x), roll tips
    # the plate toward -y (R = Rx·Ry·Rz), so the ML support angle is -roll.
    support_ap, support_ml = tilt[1], -tilt[0]
    support_rate_ap, support_rate_ml = angular_velocity[1], -angular_velocity[0]
    half_width, half_breadth = p[P_HALF_WIDTH], p[P_HALF_BREADTH]
    lateral_reach = half_width + half_breadth
    feedback_length, feedforward_length = int(p[P_FB_STEPS]), int(p[P_FF_STEPS])
    total_force = 0.0
    plate_torque_ap = 0.0
    torque_ml = 0.0
    tension = 0.0
    right_force = left_force = 0.0
    for _ in range(int(p[P_SUBSTEPS])):
        # Support displacement relative to the room, by a leaky double integration (drift-free).
        leak = p[P_LEAK_RATE]
        for axis in range(3):
            s[S_SUPPORT_VX + axis] += (acceleration[axis] - leak * s[S_SUPPORT_VX + axis]) * dt
            s[S_SUPPORT_X + axis] += (s[S_SUPPORT_VX + axis] - leak * s[S_SUPPORT_X + axis]) * dt
        # Low-pass (Ornstein–Uhlenbeck) sensory and motor noise, exactly discretised.
        for index in range(2):
            s[S_SENSORY_NOISE_AP + index] = s[S_SENSORY_NOISE_AP + index] * p[P_SENSORY_DECAY] + p[
                P_SENSORY_DRIVE
            ] * _next_gaussian(rng_state)
            s[S_MOTOR_NOISE_AP + index] = s[S_MOTOR_NOISE_AP + index] * p[P_MOTOR_DECAY] + p[
                P_MOTOR_DRIVE
            ] * _next_gaussian(rng_state)

        theta_ap, omega_ap = s[S_THETA_AP], s[S_OMEGA_AP]
        theta_ml, omega_ml = s[S_THETA_ML], s[S_OMEGA_ML]
        relative_ap, relative_rate_ap = theta_ap - support_ap, omega_ap - support_rate_ap
        relative_ml, relative_rate_ml = theta_ml - support_ml, omega_ml - support_rate_ml
        # Peterka's sensory integration: proprioception sees the angle to the foot, graviception the
        # angle to vertical.
        weight = p[P_WPROP]
        sensed_ap = weight * relative_ap + (1.0 - weight) * theta_ap + s[S_SENSORY_NOISE_AP]
        sensed_rate_ap = weight * relative_rate_ap + (1.0 - weight) * omega_ap
        sensed_ml = weight * relative_ml + (1.0 - weight) * theta_ml + s[S_SENSORY_NOISE_ML]
        sensed_rate_ml = weight * relative_rate_ml + (1.0 - weight) * omega_ml

        # Transport delays: read the oldest sample, then overwrite it with the newest.
        index = int(s[S_DELAY_INDEX])
        delayed_ap, delayed_rate_ap = delay[index, 0], delay[index, 1]
        delayed_ml, delayed_rate_ml = delay[index, 2], delay[index, 3]
        delay[index, 0], delay[index, 1] = sensed_ap, sensed_rate_ap
        delay[index, 2], delay[index, 3] = sensed_ml, sensed_rate_ml
        s[S_DELAY_INDEX] = (index + 1) % feedback_length
        index = int(s[S_FF_INDEX])
        sensed_support_ax, sensed_support_ay = delay[index, 4], delay[index, 5]
        delay[index, 4], delay[index, 5] = acceleration[0], acceleration[1]
        s[S_FF_INDEX] = (index + 1) % feedforward_length

        # Delayed PD on the sensed angle, plus the feedforward that cancels a share of the support's
        # inertial torque m·h·a (the automatic postural response to a sensed support acceleration).
        inertial_gain = p[P_FF_GAIN] * mass * height
        # The muscles' activation dynamics, critically damped at ω, with the anticipation's lead (1 + 2s/ω)
        # that times a predictable cue's torque: ω²(1 + 2s/ω)/(s + ω)². Below 1 Hz it passes the push within
        # 4 % and 1°; at 89 Hz it passes 6 %. Canonical form: x1' = x2, x2' = u − ω²x1 − 2ωx2,
        # torque = ω²x1 + 2ωx2 (semi-implicit Euler).
        omega_act = p[P_ACTIVATION_OMEGA]
        feedforward_ap = feedforward_ml = 0.0
        for state_index, drive in (
            (S_FF_TORQUE_AP, -inertial_gain * sensed_support_ax),
            (S_FF_TORQUE_ML, -inertial_gain * sensed_support_ay),
        ):
            s[state_index + 1] += (
                drive - omega_act * omega_act * s[state_index] - 2.0 * omega_act * s[state_index + 1]
            ) * dt
            s[state_index] += s[state_index + 1] * dt
            torque = omega_act * omega_act * s[state_index] + 2.0 * omega_act * s[state_index + 1]
            if state_index == S_FF_TORQUE_AP:
                feedforward_ap = torque
            else:
                feedforward_ml = torque
        active_ap = p[P_KP] * delayed_ap + p[P_KD] * delayed_rate_ap + feedforward_ap
        active_ml = p[P_KP] * delayed_ml + p[P_KD] * delayed_rate_ml + feedforward_ml
        torque_max = p[P_TORQUE_MAX]
        torque_ap = _clamp(active_ap, -torque_max, torque_max)
        torque_ml = _clamp(active_ml, -torque_max, torque_max)
        torque_ap += p[P_KPAS] * relative_ap + p[P_BPAS] * relative_rate_ap + s[S_MOTOR_NOISE_AP]
        torque_ml += p[P_KPAS] * relative_ml + p[P_BPAS] * relative_rate_ml + s[S_MOTOR_NOISE_ML]

        tension = _rope_tension(p, s, rope)
        # Vertical load on the feet: weight, support heave, the COM's own vertical acceleration (last
        # step's angular acceleration) and what the harness carries.
        sin_ap, cos_ap = math.sin(theta_ap), math.cos(theta_ap)
        sin_ml, cos_ml = math.sin(theta_ml), math.cos(theta_ml)
        com_vertical_acceleration = -height * (
            (s[S_ACCEL_AP] * sin_ap + omega_ap**2 * cos_ap) * cos_ml
            + (s[S_ACCEL_ML] * sin_ml + omega_ml**2 * cos_ml) * cos_ap
            - 2.0 * omega_ap * omega_ml * sin_ap * sin_ml
        )
        effective_gravity = GRAVITY_M_S2 + acceleration[2]
        body_force = mass * (effective_gravity + com_vertical_acceleration) - tension * rope[2]

        # Once balance is lost (see below) the patient reacts after a reaction time: a step, a grab of
        # the rail, or nothing, when the legs give way and the harness catches the body.
        response = int(s[S_RESPONSE])
        reacting = 0.0
        if response != RESPONSE_NONE:
            s[S_RESPONSE_TIME] += dt
            reacting = s[S_RESPONSE_TIME] - p[P_REACTION]
        rescue_share = 0.0  # how much of the rescue torque (planted foot, held rail) acts
        plate_share = 1.0  # the share of the body's load that stays on the plates
        stepping_foot_share = 1.0  # the stepping foot's own share of its normal load
        if response == RESPONSE_STEP and reacting > 0.0:
            stepping_foot_share = max(0.0, 1.0 - reacting / LIFT_OFF_S)
            if reacting > LIFT_OFF_S + p[P_SWING]:  # landed beside the plate: half the weight is off it
                rescue_share, plate_share = 1.0, 0.5
        elif response == RESPONSE_GRAB and reacting > 0.0:
            rescue_share = min(1.0, reacting / GRAB_RAMP_S)
        elif response == RESPONSE_CATCH and reacting > 0.0:
            plate_share = 1.0 - p[P_BUCKLE] * min(1.0, reacting / BUCKLE_RAMP_S)
        if response == RESPONSE_CATCH and reacting > 0.0 and s[S_DROP] < MAX_DROP_M:
            # The legs carry only part of the load: the body sags until the rope takes the rest.
            drop_acceleration = (1.0 - plate_share) * effective_gravity - tension * rope[2] / mass
            s[S_DROP_RATE] = max(s[S_DROP_RATE] + drop_acceleration * dt, 0.0)
            s[S_DROP] = min(s[S_DROP] + s[S_DROP_RATE] * dt, MAX_DROP_M)
            total_force = max(mass * effective_gravity * plate_share, 0.0) + p[P_FEET_MASS] * effective_gravity
        else:
            if response == RESPONSE_CATCH:
                s[S_DROP_RATE] = 0.0  # fully sagged: the legs and the rope hold the body
                plate_share = 1.0
            total_force = max(body_force * plate_share, 0.0) + p[P_FEET_MASS] * effective_gravity
        if response == RESPONSE_GRAB:
            total_force = max(total_force - rescue_share * p[P_GRAB_LOAD] * mass * GRAVITY_M_S2, 0.0)

        # The ankles keep the COP within a functional part of the foot and the hips (trunk counter-rotation,
        # a moment that passes through no plate) take the excess; only once the hips are saturated does the
        # COP go to the edge of the foot, which it cannot leave.
        demanded_ap = torque_ap
        torque_ap = _clamp(
            demanded_ap,
            -total_force * FUNCTIONAL_BASE_FRACTION * p[P_HEEL],
            total_force * FUNCTIONAL_BASE_FRACTION * p[P_TOE],
        )
        hip_ap = _clamp(demanded_ap - torque_ap, -p[P_HIP_MAX], p[P_HIP_MAX])
        torque_ap = _clamp(demanded_ap - hip_ap, -total_force * p[P_HEEL], total_force * p[P_TOE])
        torque_ml = _clamp(torque_ml, -total_force * lateral_reach, total_force * lateral_reach)
        plate_torque_ap = torque_ap
        torque_ap += hip_ap
        # A planted step or a held rail adds its own moment, through neither plate.
        rescue_ap = rescue_share * (p[P_RESCUE_K] * theta_ap + p[P_RESCUE_C] * omega_ap)
        rescue_ml = rescue_share * (p[P_RESCUE_K] * theta_ml + p[P_RESCUE_C] * omega_ml)

        # Plate loads: within the stance the ML moment is made by sharing load between the feet.
        net_cop_ml = torque_ml / total_force if total_force > 1e-9 else 0.0
        left_share = _clamp(0.5 + net_cop_ml / (2.0 * half_width), 0.0, 1.0)
        right_force, left_force = total_force * (1.0 - left_share), total_force * left_share
        if response == RESPONSE_STEP:
            if s[S_STEP_FOOT] == 0.0:
                right_force *= stepping_foot_share
                left_force = total_force - right_force
            else:
                left_force *= stepping_foot_share
                right_force = total_force - left_force

        attach = p[P_ATTACH_HEIGHT]
        lever_x, lever_y, lever_z = attach * sin_ap, attach * sin_ml, attach * cos_ap * cos_ml
        force_x, force_y, force_z = tension * rope[0], tension * rope[1], tension * rope[2]
        harness_moment_ap = lever_z * force_x - lever_x * force_z
        harness_moment_ml = lever_z * force_y - lever_y * force_z

        accel_ap = (
            mass * height * (effective_gravity * sin_ap - acceleration[0] * cos_ap)
            - torque_ap
            - rescue_ap
            + harness_moment_ap
        ) / inertia
        accel_ml = (
            mass * height * (effective_gravity * sin_ml - acceleration[1] * cos_ml)
            - torque_ml
            - rescue_ml
            + harness_moment_ml
        ) / inertia
        s[S_ACCEL_AP], s[S_ACCEL_ML] = accel_ap, accel_ml
        # Semi-implicit Euler: velocity first, then angle with the new velocity (energy-stable).
        s[S_OMEGA_AP] += accel_ap * dt
        s[S_OMEGA_ML] += accel_ml * dt
        s[S_THETA_AP] += s[S_OMEGA_AP] * dt
        s[S_THETA_ML] += s[S_OMEGA_ML] * dt
        for angle, rate in ((S_THETA_AP, S_OMEGA_AP), (S_THETA_ML, S_OMEGA_ML)):
            if abs(s[angle]) > FLOOR_ANGLE_RAD:  # the body lands on the frame: an inelastic stop
                s[angle] = math.copysign(FLOOR_ANGLE_RAD, s[angle])
                s[rate] = 0.0
        s[S_TIME] += dt

        # Balance is lost once the extrapolated COM (Hof et al. 2005: x + v/ω0, ω0 = √(g/h)) leaves the
        # base of support: no centre of pressure inside the feet can bring the body back. Leaning far
        # enough to take up the harness slack is being caught: a fall as well.
        if s[S_FALLEN] == 0.0:
            com_ap, com_ml = height * math.sin(s[S_THETA_AP]), height * math.sin(s[S_THETA_ML])
            xcom_ap = com_ap + height * math.cos(s[S_THETA_AP]) * s[S_OMEGA_AP] / p[P_OMEGA0]
            xcom_ml = com_ml + height * math.cos(s[S_THETA_ML]) * s[S_OMEGA_ML] / p[P_OMEGA0]
            outside = xcom_ap > p[P_TOE] or xcom_ap < -p[P_HEEL] or abs(xcom_ml) > lateral_reach
            if outside or tension > 0.0:
                s[S_FALLEN] = 1.0
                s[S_FALL_ONSET] = s[S_TIME]
                choice = _next_uniform(rng_state)
                if choice < p[P_STEP_P]:
                    s[S_RESPONSE] = RESPONSE_STEP
                elif choice < p[P_STEP_P] + p[P_GRAB_P]:
                    s[S_RESPONSE] = RESPONSE_GRAB
                else:
                    s[S_RESPONSE] = RESPONSE_CATCH
                s[S_STEP_FOOT] = 0.0 if left_share >= 0.5 else 1.0  # the unloaded foot steps

    _write_readings(p, s, rng_state, right_force, left_force, plate_torque_ap, torque_ml, tension, out)


@numba.njit(cache=True)
def _write_readings(
    p: np.ndarray,
    s: np.ndarray,
    rng_state: np.ndarray,
    right_force: float,
    left_force: float,
    torque_ap: float,
    torque_ml: float,
    tension: float,
    out: np.ndarray,
) -> None:
    """Plate forces and COPs. A sensor's noise cannot put the COP outside the sole that makes it."""
    half_width, half_breadth = p[P_HALF_WIDTH], p[P_HALF_BREADTH]
    heel, toe = p[P_HEEL], p[P_TOE]
    total_force = right_force + left_force
    cop_ap = 0.0
    net_cop_ml = 0.0
    if total_force > 1e-9:
        cop_ap = torque_ap / total_force
        net_cop_ml = torque_ml / total_force
    # Beyond the stance width one foot carries all and its own COP moves toward its outer edge.
    right_cop_ml = min(net_cop_ml + half_width, 0.0)
    left_cop_ml = max(net_cop_ml - half_width, 0.0)
    if s[S_RESPONSE] == RESPONSE_STEP:
        right_cop_ml = left_cop_ml = 0.0  # one foot stands alone
    out[O_FZ_RIGHT] = right_force + p[P_FORCE_NOISE] * _next_gaussian(rng_state)
    out[O_FZ_LEFT] = left_force + p[P_FORCE_NOISE] * _next_gaussian(rng_state)
    out[O_COP_RIGHT_X] = _clamp(cop_ap + p[P_COP_NOISE] * _next_gaussian(rng_state), -heel, toe)
    out[O_COP_RIGHT_Y] = _clamp(right_cop_ml + p[P_COP_NOISE] * _next_gaussian(rng_state), -half_breadth, half_breadth)
    out[O_COP_LEFT_X] = _clamp(cop_ap + p[P_COP_NOISE] * _next_gaussian(rng_state), -heel, toe)
    out[O_COP_LEFT_Y] = _clamp(left_cop_ml + p[P_COP_NOISE] * _next_gaussian(rng_state), -half_breadth, half_breadth)
    out[O_HARNESS] = tension + p[P_HARNESS_NOISE] * _next_gaussian(rng_state)
    out[O_SWAY_AP] = s[S_THETA_AP]
    out[O_SWAY_ML] = s[S_THETA_ML]
    out[O_FALLEN] = s[S_FALLEN]
    out[O_FALL_ONSET] = s[S_FALL_ONSET]
    out[O_TIME] = s[S_TIME]
    out[O_RESPONSE] = s[S_RESPONSE]
    out[O_DROP] = s[S_DROP]


@numba.njit(cache=True)
def _simulate_kernel(
    p: np.ndarray,
    s: np.ndarray,
    delay: np.ndarray,
    rng_state: np.ndarray,
    accelerations: np.ndarray,
    tilts: np.ndarray,
    angular_velocities: np.ndarray,
    outputs: np.ndarray,
) -> None:
    rope = np.zeros(3)
    for row in range(accelerations.shape[0]):
        _patient_step(
            p, s, delay, rng_state, rope, accelerations[row], tilts[row], angular_velocities[row], outputs[row]
        )


# --- front ends --------------------------------------------------------------------------------------


def _validate_sample_period(sample_period_s: float) -> int:
    require_in_range("sample_period_s", sample_period_s, 0.0, 0.02, low_open=True)
    return max(1, math.ceil(sample_period_s / MAX_INTERNAL_STEP_S - 1e-9))


def _parameter_vector(params: PatientParameters, sample_period_s: float) -> np.ndarray:
    substeps = _validate_sample_period(sample_period_s)
    dt = sample_period_s / substeps
    mgh = params.gravity_stiffness_n_m
    foot = params.foot
    vector = np.zeros(P_SIZE)
    vector[P_MASS] = params.pendulum_mass_kg
    vector[P_FEET_MASS] = params.body_mass_kg - params.pendulum_mass_kg
    vector[P_COM_HEIGHT] = params.com_height_above_ankle_m
    vector[P_INERTIA] = params.moment_of_inertia_kg_m2
    vector[P_HEEL], vector[P_TOE], vector[P_HALF_BREADTH] = foot.heel_m, foot.toe_m, foot.half_breadth_m
    vector[P_HALF_WIDTH] = 0.5 * params.stance_width_m
    vector[P_ATTACH_HEIGHT] = params.harness_attachment_above_ankle_m
    vector[P_ANCHOR_HEIGHT] = params.harness_anchor_above_attachment_m
    vector[P_ROPE_REST] = params.harness_anchor_above_attachment_m + params.harness_slack_m
    vector[P_ROPE_K] = params.harness_stiffness_n_m
    vector[P_ROPE_C] = params.harness_damping_n_s_m
    vector[P_KP] = params.proportional_gain_per_mgh * mgh
    vector[P_KD] = params.derivative_gain_per_mgh_s * mgh
    vector[P_KPAS] = params.passive_stiffness_per_mgh * mgh
    vector[P_BPAS] = params.passive_damping_per_mgh_s * mgh
    vector[P_WPROP] = params.proprioceptive_weight
    vector[P_TORQUE_MAX] = params.ankle_torque_max_n_m_per_kg * params.body_mass_kg
    for decay, drive, sigma, tau in (
        (P_SENSORY_DECAY, P_SENSORY_DRIVE, params.sensory_noise_rad, params.sensory_noise_time_constant_s),
        (P_MOTOR_DECAY, P_MOTOR_DRIVE, params.motor_noise_per_mgh * mgh, params.motor_noise_time_constant_s),
    ):
        vector[decay] = math.exp(-dt / tau)
        vector[drive] = sigma * math.sqrt(1.0 - vector[decay] ** 2)  # keeps the stationary std at sigma
    vector[P_FORCE_NOISE] = params.plate_force_noise_n
    vector[P_COP_NOISE] = params.plate_cop_noise_m
    vector[P_HARNESS_NOISE] = params.harness_load_noise_n
    vector[P_DT] = sample_period_s
    vector[P_SUBSTEPS] = substeps
    vector[P_LEAK_RATE] = 1.0 / SUPPORT_LEAK_TIME_CONSTANT_S
    vector[P_FF_GAIN] = params.acceleration_feedforward_gain
    vector[P_FB_STEPS], vector[P_FF_STEPS] = _delay_steps(params, dt)
    vector[P_OMEGA0] = math.sqrt(GRAVITY_M_S2 / params.com_height_above_ankle_m)
    vector[P_STEP_P] = params.step_probability
    vector[P_GRAB_P] = params.grab_probability
    vector[P_REACTION] = params.protective_reaction_s
    vector[P_SWING] = params.step_swing_s
    vector[P_GRAB_LOAD] = params.grab_load_fraction_bw
    vector[P_BUCKLE] = params.leg_buckle_fraction
    vector[P_RESCUE_K] = RESCUE_STIFFNESS_PER_MGH * mgh
    vector[P_RESCUE_C] = RESCUE_DAMPING_PER_MGH_S * mgh
    vector[P_HIP_MAX] = params.hip_torque_max_n_m_per_kg * params.body_mass_kg
    vector[P_ACTIVATION_OMEGA] = 2.0 * math.pi * params.muscle_activation_frequency_hz
    return vector


def _delay_steps(params: PatientParameters, internal_step_s: float) -> tuple[int, int]:
    """Ring-buffer lengths of the feedback and the feedforward delays, in internal steps."""
    return (
        max(1, round(params.feedback_delay_s / internal_step_s)),
        max(1, round(params.acceleration_feedforward_delay_s / internal_step_s)),
    )


# The harness anchor is fixed in the room, so the feet's displacement under it matters; it is the
# double integral of the support acceleration, leaked with a time constant far longer than any
# perturbation pulse so that integration drift cannot slacken or tighten the rope over a session.
SUPPORT_LEAK_TIME_CONSTANT_S = 30.0


def _initial_state(params: PatientParameters, sample_period_s: float, seed: int) -> tuple[np.ndarray, ...]:
    substeps = _validate_sample_period(sample_period_s)
    internal_step_s = sample_period_s / substeps
    state = np.zeros(S_SIZE)
    state[S_FALL_ONSET] = math.nan
    delay = np.zeros((max(_delay_steps(params, internal_step_s)), 6))  # sensed angles, then support accel
    rng_state = np.random.SeedSequence(seed).generate_state(1, np.uint64)
    return state, delay, rng_state


class PatientSample:
    """One step's readings. Arrays are views of the patient's own buffer, overwritten by the next step."""

    __slots__ = ("_out", "plate_cop_m", "plate_force_z_n", "sway_angle_rad")

    def __init__(self, out: np.ndarray) -> None:
        self._out = out
        self.plate_force_z_n = out[O_FZ_RIGHT : O_FZ_LEFT + 1]  # (right, left), N
        self.plate_cop_m = out[O_COP_RIGHT_X : O_COP_LEFT_Y + 1].reshape(2, 2)  # [foot, (x, y)]
        self.sway_angle_rad = out[O_SWAY_AP : O_SWAY_ML + 1]  # (AP forward +, ML to the left +)

    @property
    def harness_load_n(self) -> float:
        return float(self._out[O_HARNESS])

    @property
    def fallen(self) -> bool:
        return bool(self._out[O_FALLEN])

    @property
    def fall_onset_s(self) -> float:
        """Time of the fall onset (NaN while standing), on the patient's own clock."""
        return float(self._out[O_FALL_ONSET])

    @property
    def time_s(self) -> float:
        return float(self._out[O_TIME])

    @property
    def fall_response(self) -> str:
        """What the patient did once balance was lost: "step", "grab", "harness_catch" (or "")."""
        return RESPONSE_NAMES.get(int(self._out[O_RESPONSE]), "")


class SimulatedPatient:
    """The streaming front end: one `step` per control tick, no allocation per step."""

    def __init__(self, params: PatientParameters, sample_period_s: float, seed: int = 0) -> None:
        self.params = params
        self.sample_period_s = sample_period_s
        self.seed = seed
        self._params = _parameter_vector(params, sample_period_s)
        self._rope = np.zeros(3)
        self._out = np.zeros(O_SIZE)
        self._sample = PatientSample(self._out)
        self.reset()

    def reset(self) -> None:
        """Upright and still, noise restarted from the seed."""
        self._state, self._delay, self._rng = _initial_state(self.params, self.sample_period_s, self.seed)
        self._out[:] = 0.0
        self._out[O_FZ_RIGHT] = self._out[O_FZ_LEFT] = 0.5 * self.params.body_weight_n
        self._out[O_FALL_ONSET] = math.nan

    def step(
        self,
        support_acceleration_m_s2: np.ndarray,
        support_tilt_rad: np.ndarray,
        support_angular_velocity_rad_s: np.ndarray,
    ) -> PatientSample:
        """Advance one sample period. Support acceleration (3,) is the foot plates' linear acceleration in
        the world frame (gravity excluded); tilt (2,) is (roll, pitch); angular velocity (3,) in rad/s."""
        if support_acceleration_m_s2.shape != (3,) or support_tilt_rad.shape != (2,):
            raise ParameterError(
                "support_acceleration_m_s2/support_tilt_rad",
                (support_acceleration_m_s2.shape, support_tilt_rad.shape),
                "shapes must be (3,) and (2,)",
            )
        if support_angular_velocity_rad_s.shape != (3,):
            raise ParameterError(
                "support_angular_velocity_rad_s", support_angular_velocity_rad_s.shape, "shape must be (3,)"
            )
        _patient_step(
            self._params,
            self._state,
            self._delay,
            self._rng,
            self._rope,
            support_acceleration_m_s2,
            support_tilt_rad,
            support_angular_velocity_rad_s,
            self._out,
        )
        return self._sample

    @property
    def fallen(self) -> bool:
        return bool(self._state[S_FALLEN])

    @property
    def fall_onset_s(self) -> float:
        return float(self._state[S_FALL_ONSET])


@dataclass(frozen=True)
class PatientTrajectory:
    """A whole run: (N,) or (N, k) arrays per reading, time at the end of each sample."""

    time_s: np.ndarray
    plate_force_z_n: np.ndarray  # (N, 2)
    plate_cop_m: np.ndarray  # (N, 2, 2)
    harness_load_n: np.ndarray  # (N,)
    sway_angle_rad: np.ndarray  # (N, 2)
    fallen: np.ndarray  # (N,) bool
    fall_onset_s: float  # NaN if the patient stayed standing
    fall_response: str = ""  # "step", "grab" or "harness_catch" once balance was lost
    body_drop_m: np.ndarray | None = None  # (N,) the body's sag when the legs gave way (ground truth)


def _as_motion(name: str, values: np.ndarray, width: int, count: int | None) -> np.ndarray:
    array = np.ascontiguousarray(values, dtype=float)
    if array.ndim != 2 or array.shape[1] != width or (count is not None and array.shape[0] != count):
        expected = f"({count if count is not None else 'N'}, {width})"
        raise ParameterError(name, array.shape, f"shape must be {expected}")
    if not np.all(np.isfinite(array)):
        raise ParameterError(name, "non-finite", "every value must be finite")
    return array


def simulate(
    params: PatientParameters,
    sample_period_s: float,
    seed: int,
    support_acceleration_m_s2: np.ndarray,
    support_tilt_rad: np.ndarray,
    support_angular_velocity_rad_s: np.ndarray,
) -> PatientTrajectory:
    """The batch front end: the same kernel and noise stream as `SimulatedPatient.step`, over (N, ·) inputs."""
    accelerations = _as_motion("support_acceleration_m_s2", support_acceleration_m_s2, 3, None)
    count = accelerations.shape[0]
    tilts = _as_motion("support_tilt_rad", support_tilt_rad, 2, count)
    angular_velocities = _as_motion("support_angular_velocity_rad_s", support_angular_velocity_rad_s, 3, count)
    vector = _parameter_vector(params, sample_period_s)
    state, delay, rng_state = _initial_state(params, sample_period_s, seed)
    outputs = np.empty((count, O_SIZE))
    _simulate_kernel(vector, state, delay, rng_state, accelerations, tilts, angular_velocities, outputs)
    return PatientTrajectory(
        time_s=outputs[:, O_TIME].copy(),
        plate_force_z_n=outputs[:, O_FZ_RIGHT : O_FZ_LEFT + 1].copy(),
        plate_cop_m=outputs[:, O_COP_RIGHT_X : O_COP_LEFT_Y + 1].reshape(count, 2, 2).copy(),
        harness_load_n=outputs[:, O_HARNESS].copy(),
        sway_angle_rad=outputs[:, O_SWAY_AP : O_SWAY_ML + 1].copy(),
        fallen=outputs[:, O_FALLEN] > 0.5,
        fall_onset_s=float(state[S_FALL_ONSET]),
        fall_response=RESPONSE_NAMES.get(int(state[S_RESPONSE]), ""),
        body_drop_m=outputs[:, O_DROP].copy(),
    )


# --- perturbations: support motion for trials and simulated cohorts -------------------------------


@dataclass(frozen=True)
class Perturbation:
    """One support perturbation.

    "translation": a two-lobed sine acceleration pulse (out, then brake) of `magnitude` m/s² peak along
    `direction_rad` (0 = anterior, π/2 = to the left), lasting `duration_s`; the support ends at rest,
    displaced. "tilt": a raised-cosine tilt of `magnitude` rad about the horizontal axis that tips
    the plate toward `direction_rad` over `duration_s`, held as long, then returned as slowly.
    """

    kind: str
    onset_s: float
    direction_rad: float
    magnitude: float
    duration_s: float

    def __post_init__(self) -> None:
        if self.kind not in ("translation", "tilt"):
            raise ParameterError("kind", self.kind, "must be 'translation' or 'tilt'")
        require_in_range("onset_s", self.onset_s, 0.0, 1e6)
        require_in_range("direction_rad", self.direction_rad, -2 * math.pi, 2 * math.pi)
        limit = 20.0 if self.kind == "translation" else math.radians(25.0)
        require_in_range("magnitude", self.magnitude, 0.0, limit)
        require_in_range("duration_s", self.duration_s, 0.05, 10.0)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class SupportMotion:
    """Support motion sampled at the end of each period: acceleration (N,3), tilt (N,2) roll/pitch,
    angular velocity (N,3)."""

    time_s: np.ndarray
    acceleration_m_s2: np.ndarray
    tilt_rad: np.ndarray
    angular_velocity_rad_s: np.ndarray


def support_motion(perturbations: list[Perturbation], duration_s: float, sample_period_s: float) -> SupportMotion:
    """Superpose the perturbations' support motions on a quiet support, vectorised over time."""
    require_in_range("duration_s", duration_s, 0.0, 24 * 3600.0, low_open=True)
    _validate_sample_period(sample_period_s)
    time_s = np.arange(1, round(duration_s / sample_period_s) + 1) * sample_period_s
    acceleration = np.zeros((len(time_s), 3))
    tip = np.zeros((len(time_s), 2))  # tilt angle as a vector toward where the plate tips (x, y)
    tip_rate = np.zeros((len(time_s), 2))
    for perturbation in perturbations:
        local = time_s - perturbation.onset_s
        direction = np.array([math.cos(perturbation.direction_rad), math.sin(perturbation.direction_rad)])
        if perturbation.kind == "translation":
            active = (local >= 0.0) & (local <= perturbation.duration_s)
            pulse = np.where(active, np.sin(2 * math.pi * local / perturbation.duration_s), 0.0)
            acceleration[:, :2] += perturbation.magnitude * pulse[:, None] * direction
        else:
            angle, rate = _tilt_profile(local, perturbation.magnitude, perturbation.duration_s)
            tip += angle[:, None] * direction
            tip_rate += rate[:, None] * direction
    # Tipping the plate toward +x is +pitch; toward +y is -roll (R = Rx·Ry·Rz).
    tilt = np.column_stack([-tip[:, 1], tip[:, 0]])
    angular_velocity = np.column_stack([-tip_rate[:, 1], tip_rate[:, 0], np.zeros(len(time_s))])
    return SupportMotion(time_s, acceleration, tilt, angular_velocity)


def _tilt_profile(local_s: np.ndarray, amplitude_rad: float, ramp_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Raised-cosine ramp up over `ramp_s`, hold `ramp_s`, ramp down over 2·`ramp_s`: angle and rate."""
    angle = np.zeros_like(local_s)
    rate = np.zeros_like(local_s)
    rising = (local_s >= 0) & (local_s < ramp_s)
    holding = (local_s >= ramp_s) & (local_s < 2 * ramp_s)
    falling = (local_s >= 2 * ramp_s) & (local_s < 4 * ramp_s)
    phase_up = math.pi * local_s[rising] / ramp_s
    angle[rising] = 0.5 * amplitude_rad * (1 - np.cos(phase_up))
    rate[rising] = 0.5 * amplitude_rad * math.pi / ramp_s * np.sin(phase_up)
    angle[holding] = amplitude_rad
    phase_down = math.pi * (local_s[falling] - 2 * ramp_s) / (2 * ramp_s)
    angle[falling] = 0.5 * amplitude_rad * (1 + np.cos(phase_down))
    rate[falling] = -0.5 * amplitude_rad * math.pi / (2 * ramp_s) * np.sin(phase_down)
    return angle, rate


def simulate_trial(
    params: PatientParameters,
    perturbations: list[Perturbation],
    duration_s: float,
    sample_period_s: float,
    seed: int,
) -> tuple[SupportMotion, PatientTrajectory]:
    """Support motion for the perturbations and the patient's response to it."""
    motion = support_motion(perturbations, duration_s, sample_period_s)
    trajectory = simulate(
        params, sample_period_s, seed, motion.acceleration_m_s2, motion.tilt_rad, motion.angular_velocity_rad_s
    )
    return motion, trajectory


def random_patient(rng: np.random.Generator, impaired_share: float = 0.5) -> PatientParameters:
    """A plausible adult: height ~ N(1.72, 0.09) m, BMI ~ N(25, 3.5) kg/m², preset by `impaired_share`."""
    require_in_range("impaired_share", impaired_share, 0.0, 1.0)
    height_m = float(np.clip(rng.normal(1.72, 0.09), 1.5, 1.95))
    bmi = float(np.clip(rng.normal(25.0, 3.5), 18.5, 35.0))
    preset = "impaired" if rng.random() < impaired_share else "healthy"
    return PatientParameters.preset(preset, body_mass_kg=round(bmi * height_m**2, 1), height_m=round(height_m, 3))


def random_perturbations(
    rng: np.random.Generator, duration_s: float, *, mean_interval_s: float = 12.0, settle_s: float = 5.0
) -> list[Perturbation]:
    """Pulses at random onsets (at least `settle_s` apart and from the start), random direction and size.

    Translations peak at 0.3–3 m/s² over 0.3–0.6 s (the paper's robot reaches 5 m/s²; the support moves
    at most a·T²/2π ≈ 0.17 m, well inside the harness slack's reach); tilts reach 0.5–8°
    over 0.3–1.0 s. Sizes are drawn log-uniformly so that mild and hard pulses both occur."""
    perturbations = []
    onset_s = settle_s + rng.exponential(mean_interval_s / 2)
    while onset_s < duration_s - settle_s:
        direction_rad = float(rng.uniform(-math.pi, math.pi))
        if rng.random() < 0.5:
            magnitude = float(np.exp(rng.uniform(math.log(0.3), math.log(3.0))))
            perturbation = Perturbation("translation", onset_s, direction_rad, magnitude, float(rng.uniform(0.3, 0.6)))
        else:
            magnitude = float(np.exp(rng.uniform(math.log(math.radians(0.5)), math.log(math.radians(8.0)))))
            perturbation = Perturbation("tilt", onset_s, direction_rad, magnitude, float(rng.uniform(0.3, 1.0)))
        perturbations.append(perturbation)
        onset_s += settle_s + 4 * perturbation.duration_s + rng.exponential(mean_interval_s)
    return perturbations
