"""Vestibular models against their analytic DC gains, poles and step responses (Formulas 14–15)."""

from __future__ import annotations

import math

import control
import numpy as np
import pytest

from core.shaping import ParameterError
from core.vestibular import (
    CanalParameters,
    OtolithParameters,
    PerceptionThresholds,
    VestibularModel,
    VestibularParameters,
    canal_transfer_function,
    otolith_transfer_function,
)

DT = 0.001


def test_otolith_dc_gain_pole_and_zero_are_table_2() -> None:
    system = otolith_transfer_function(OtolithParameters())
    assert control.dcgain(system) == pytest.approx(0.4)
    assert sorted(np.real(control.poles(system))) == pytest.approx(sorted([-1 / 5.33, -1 / 0.66]))
    assert np.real(control.zeros(system)) == pytest.approx([-1 / 13.2])


def test_canal_constants_follow_the_formula_not_table_3_labels() -> None:
    """T_L = 6.1 s (long), T_s = 0.1 s, T_a = 30 s; the denominator is exact (no `1/Tl*Ts` = Ts/Tl slip)."""
    system = canal_transfer_function(CanalParameters())
    long_s, short_s, adaptation_s = 6.1, 0.1, 30.0
    expected_den = [
        long_s * short_s * adaptation_s,
        long_s * short_s + long_s * adaptation_s + short_s * adaptation_s,
        long_s + short_s + adaptation_s,
        1.0,
    ]
    assert np.asarray(system.den[0][0]) == pytest.approx(expected_den)
    assert np.asarray(system.num[0][0]) == pytest.approx([long_s * adaptation_s, 0.0, 0.0])
    assert control.dcgain(system) == pytest.approx(0.0, abs=1e-12)
    assert sorted(np.real(control.poles(system))) == pytest.approx(sorted([-1 / 6.1, -1 / 0.1, -1 / 30.0]))
    # Mid-band the canal passes angular velocity at unit gain: T_L T_a s² / (T_L s · T_a s · 1).
    assert abs(control.evalfr(system, 1j * 1.0)) == pytest.approx(1.0, abs=0.03)


def test_literature_defaults_per_axis() -> None:
    params = VestibularParameters()
    assert [c.long_time_constant_s for c in params.canals] == [6.1, 5.3, 10.2]
    assert params.thresholds.specific_force_m_s2 == (0.17, 0.17, 0.28)
    assert np.degrees(params.thresholds.angular_velocity_rad_s) == pytest.approx([3.0, 3.6, 2.6])


def test_discrete_otolith_step_matches_the_analytic_response() -> None:
    tau_a, tau_l, tau_s, gain = 13.2, 5.33, 0.66, 0.4
    time_s = np.arange(int(30 / DT)) * DT
    step = np.zeros((len(time_s), 3))
    step[:, 0] = 1.0
    perceived = VestibularModel(sample_period_s=DT).perceive_specific_force(step)[:, 0]
    analytic = gain * (
        1.0
        - (tau_l - tau_a) / (tau_l - tau_s) * np.exp(-time_s / tau_l)
        - (tau_a - tau_s) / (tau_l - tau_s) * np.exp(-time_s / tau_s)
    )
    # Tustin treats the step edge as a ramp over the first sample: compare after it.
    assert np.max(np.abs(perceived[1:] - analytic[1:])) < 2e-3
    assert perceived[-1] == pytest.approx(analytic[-1], rel=1e-4)


def test_discrete_canal_step_matches_the_partial_fraction_response() -> None:
    long_s, short_s, adaptation_s = 5.3, 0.1, 30.0  # pitch
    poles = np.array([-1 / long_s, -1 / short_s, -1 / adaptation_s])
    residues = [p / (short_s * np.prod([p - q for q in poles if q != p])) for p in poles]
    time_s = np.arange(int(60 / DT)) * DT
    analytic = sum(r * np.exp(p * time_s) for r, p in zip(residues, poles, strict=True))
    step = np.zeros((len(time_s), 3))
    step[:, 1] = 1.0
    perceived = VestibularModel(sample_period_s=DT).perceive_angular_velocity(step)[:, 1]
    assert np.max(np.abs(perceived[5:] - analytic[5:])) < 5e-3
    assert np.max(perceived) == pytest.approx(np.max(analytic), abs=5e-3)
    assert perceived[-1] == pytest.approx(analytic[-1], abs=1e-3)  # adaptation: the canal forgets a constant rate


@pytest.mark.parametrize(
    ("build", "field"),
    [
        (lambda: VestibularParameters(otoliths=(OtolithParameters(gain=-0.4),) * 3), "otoliths.x.gain"),
        (
            lambda: VestibularParameters(canals=(CanalParameters(short_time_constant_s=math.nan),) * 3),
            "canals.roll.short_time_constant_s",
        ),
        (
            lambda: VestibularParameters(thresholds=PerceptionThresholds(specific_force_m_s2=(0.17, 0.0, 0.28))),
            "thresholds.specific_force_m_s2",
        ),
    ],
)
def test_invalid_vestibular_parameters_name_the_field(build, field: str) -> None:
    with pytest.raises(ParameterError) as error:
        build()
    assert error.value.field == field


def test_perception_refuses_nan_and_wrong_shapes() -> None:
    model = VestibularModel(sample_period_s=DT)
    signal = np.zeros((10, 3))
    signal[4, 2] = np.nan
    with pytest.raises(ParameterError, match=r"specific_force_m_s2\[4, 2\]"):
        model.perceive_specific_force(signal)
    with pytest.raises(ValueError, match="expected"):
        model.perceive_angular_velocity(np.zeros((10, 2)))
