"""Classical washout against analytic responses, the tilt-coordination safety limits, populations and
chunking (paper §4.1, Formulas 12–13)."""

from __future__ import annotations

import math
from dataclasses import replace

import control
import numpy as np
import pytest

from core.fidelity import platform_specific_force
from core.kinematics import euler_rate_matrices, rotation_matrices
from core.physics import GRAVITY_M_S2
from core.shaping import ParameterError
from core.washout import (
    WashoutParameters,
    baseline_parameters,
    body_rates,
    design,
    paper_tilt_parameters,
    run_washout,
    washout_batch,
)

DT = 0.001


def _signals(seconds: float) -> tuple[np.ndarray, np.ndarray]:
    count = round(seconds / DT)
    return np.zeros((count, 3)), np.zeros((count, 3))


def _translational(params: WashoutParameters, numerator: list[float]) -> control.TransferFunction:
    """Formula 12 times s^k/s²: position (s), velocity (s²) or acceleration (s³) per unit inertial acceleration."""
    quadratic = [
        1.0,
        2 * params.translational_damping * params.translational_break_rad_s,
        params.translational_break_rad_s**2,
    ]
    return control.tf(numerator, np.polymul(quadratic, [1.0, params.translational_first_order_break_rad_s]))


def test_heave_step_matches_formula_12_integrated_twice() -> None:
    params = baseline_parameters()
    force, rates = _signals(20.0)
    force[:, 2] = 0.5  # heave: no tilt coordination, so the translational channel alone responds
    trajectory = washout_batch(params, DT, force, rates)
    # Tustin sees the step edge as a ramp over the sample before it: the analytic response half a sample on.
    time_s = trajectory.time_s
    measured = np.concatenate([trajectory.pose, trajectory.velocity, trajectory.acceleration], axis=1)
    for column, numerator in ((2, [1.0, 0.0]), (8, [1.0, 0.0, 0.0]), (14, [1.0, 0.0, 0.0, 0.0])):
        _, response = control.step_response(0.5 * _translational(params, numerator), T=time_s)
        analytic = np.interp(time_s + DT / 2, time_s, response)
        scale = np.max(np.abs(analytic))
        assert np.max(np.abs(measured[1:, column] - analytic[1:])) < 1e-4 * scale, column
    assert np.all(trajectory.pose[:, [0, 1, 3, 4, 5]] == 0.0)


def test_heave_ramp_settles_at_the_analytic_offset() -> None:
    """A ramp c·t through G1/s² ends at c/(ω_a² ω_a′): the washout holds a constant offset, no drift."""
    params = baseline_parameters()
    force, rates = _signals(40.0)
    slope = 0.02
    force[:, 2] = slope * np.arange(len(force)) * DT
    trajectory = washout_batch(params, DT, force, rates)
    _, analytic = control.forced_response(_translational(params, [1.0, 0.0]), T=trajectory.time_s, U=force[:, 2])
    assert np.max(np.abs(trajectory.pose[:, 2] - analytic)) < 1e-4 * np.max(np.abs(analytic))
    expected_offset = slope / (params.translational_break_rad_s**2 * params.translational_first_order_break_rad_s)
    assert trajectory.pose[-1, 2] == pytest.approx(expected_offset, rel=1e-3)
    assert trajectory.velocity[-1, 2] == pytest.approx(0.0, abs=1e-5)


@pytest.mark.parametrize(("axis", "tilt_column", "sign"), [(1, 3, 1.0), (0, 4, -1.0)])
def test_sustained_force_tilts_to_asin_f_over_g_within_the_rate_limit(axis: int, tilt_column: int, sign: float) -> None:
    params = WashoutParameters(tilt_break_rad_s=2.0)  # the filter alone would tilt at 8 °/s; the limit is 3 °/s
    force, rates = _signals(60.0)
    force[:, axis] = 2.0
    trajectory = washout_batch(params, DT, force, rates)
    tilt = trajectory.pose[:, tilt_column]
    assert tilt[-1] == pytest.approx(sign * math.asin(2.0 / GRAVITY_M_S2), abs=1e-5)
    assert np.max(np.abs(np.diff(tilt))) / DT <= params.tilt_rate_limit_rad_s * (1 + 1e-9)
    assert np.max(np.abs(trajectory.velocity[:, tilt_column])) <= params.tilt_rate_limit_rad_s * (1 + 1e-9)
    assert np.any(trajectory.tilt_rate_limited)  # the limiter really acted
    # Gravity in the right frame: once settled, the head feels the commanded force from the tilt alone.
    felt = platform_specific_force(trajectory.pose.T, trajectory.acceleration.T).T[-1]
    assert felt[axis] == pytest.approx(2.0, abs=1e-3)
    assert abs(trajectory.pose[-1, axis]) < 0.05


def test_paper_section_5_tilt_step() -> None:
    """0.2 g along Y for 10 s then 0: tilt asin(0.2) within 2 s, peak rate 0.147 rad/s, back to neutral."""
    force, rates = _signals(25.0)
    force[: int(10.0 / DT), 1] = 0.2 * GRAVITY_M_S2
    trajectory = washout_batch(paper_tilt_parameters(), DT, force, rates)
    roll = trajectory.pose[:, 3]
    final = roll[int(10.0 / DT) - 1]
    assert final == pytest.approx(math.asin(0.2), abs=2e-4)
    assert np.argmax(roll >= 0.95 * final) * DT < 2.0
    assert np.max(np.abs(trajectory.velocity[:, 3])) == pytest.approx(0.147, abs=0.002)
    assert not np.any(trajectory.tilt_rate_limited)  # bounded by its filter, as in the paper
    assert np.all(np.abs(trajectory.pose[-1000:, :3]) < 1e-3)
    assert np.all(np.abs(trajectory.pose[-1000:, 3:]) < 1e-3)


def test_scaling_limit_clips_and_reports_exactly_the_limited_samples() -> None:
    params = baseline_parameters()
    force, rates = _signals(1.0)
    force[100:200, 0] = 1.2 * params.specific_force_limit_m_s2
    rates[300:350, 2] = -1.5 * params.angular_velocity_limit_rad_s
    trajectory = washout_batch(params, DT, force, rates)
    expected = np.zeros(len(force), dtype=bool)
    expected[100:200] = expected[300:350] = True
    assert np.array_equal(trajectory.input_limited, expected)
    clipped = washout_batch(
        params,
        DT,
        np.clip(force, -params.specific_force_limit_m_s2, params.specific_force_limit_m_s2),
        np.clip(rates, -params.angular_velocity_limit_rad_s, params.angular_velocity_limit_rad_s),
    )
    assert np.array_equal(trajectory.pose, clipped.pose)
    assert not np.any(clipped.input_limited)


def test_stacked_population_design_equals_single_designs() -> None:
    force, rates = _signals(3.0)
    force[:, 0] = 1.5
    rates[:, 2] = 0.2
    population = [baseline_parameters(), paper_tilt_parameters(), WashoutParameters(translational_break_rad_s=4.0)]
    stacked = run_washout(design(population, DT), force.T, rates.T)
    for index, params in enumerate(population):
        single = washout_batch(params, DT, force, rates)
        assert np.max(np.abs(stacked.pose[index].T - single.pose)) < 1e-12
        assert np.max(np.abs(stacked.acceleration[index].T - single.acceleration)) < 1e-9


def test_body_rates_agree_with_the_kinematics_euler_rate_matrix() -> None:
    angles = np.array([[0.3, -0.4, 0.7]])
    euler_rates = np.array([0.2, -0.5, 0.9])
    base_frame = euler_rate_matrices(angles)[0] @ euler_rates
    expected = rotation_matrices(angles)[0].T @ base_frame
    assert body_rates(angles.T, euler_rates[:, None])[:, 0] == pytest.approx(expected)


def test_rotational_channel_washes_out_a_sustained_rate() -> None:
    force, rates = _signals(30.0)
    rates[:, 2] = 0.1
    trajectory = washout_batch(baseline_parameters(), DT, force, rates)
    time_s = trajectory.time_s
    # s²/(s + 1)² (ξ = 1, ω_b = 1 rad/s) on a rate step: 0.1·(1 − t)·e^(−t), then washed out.
    assert trajectory.velocity[1:5000, 5] == pytest.approx(
        0.1 * (1 - time_s[1:5000]) * np.exp(-time_s[1:5000]), abs=2e-4
    )
    assert abs(trajectory.pose[-1, 5]) < 1e-4 and abs(trajectory.velocity[-1, 5]) < 1e-5


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"translational_break_rad_s": -1.0}, "translational_break_rad_s"),
        ({"tilt_break_rad_s": -0.5}, "tilt_break_rad_s"),
        ({"translational_damping": 0.0}, "translational_damping"),
        ({"tilt_damping": -0.2}, "tilt_damping"),
        ({"rotational_break_rad_s": math.nan}, "rotational_break_rad_s"),
        ({"tilt_rate_limit_rad_s": 0.0}, "tilt_rate_limit_rad_s"),
        ({"tilt_rate_limit_rad_s": -0.1}, "tilt_rate_limit_rad_s"),
        ({"specific_force_gain": -1.0}, "specific_force_gain"),
        ({"specific_force_limit_m_s2": 9.8}, "specific_force_limit_m_s2"),
        ({"specific_force_limit_m_s2": 6.0, "tilt_damping": 0.3}, "specific_force_limit_m_s2"),
    ],
)
def test_invalid_parameters_name_field_value_and_limit(changes: dict[str, float], field: str) -> None:
    with pytest.raises(ParameterError) as error:
        WashoutParameters(**changes)
    assert error.value.field == field
    assert error.value.limit


def test_parameters_round_trip_and_unknown_keys_are_refused() -> None:
    params = paper_tilt_parameters()
    assert WashoutParameters.from_dict(params.to_dict()) == params
    with pytest.raises(ParameterError, match="omega_h"):
        WashoutParameters.from_dict({"omega_h": 2.0})


def test_bad_sample_periods_and_signals_are_refused() -> None:
    with pytest.raises(ParameterError, match="sample_period_s") as error:
        washout_batch(baseline_parameters(), 0.0, *_signals(0.01))
    assert error.value.field == "sample_period_s" and error.value.value == 0.0 and error.value.limit
    with pytest.raises(ParameterError, match="tilt_break_rad_s"):
        washout_batch(WashoutParameters(tilt_break_rad_s=5.0), 0.1, *_signals(1.0))  # too close to Nyquist
    force, rates = _signals(0.01)
    force[3, 1] = np.inf
    with pytest.raises(ParameterError, match=r"specific_force_m_s2\[3, 1\]"):
        washout_batch(baseline_parameters(), DT, force, rates)
    force[3, 1] = 0.0
    rates[7, 2] = np.nan
    with pytest.raises(ParameterError, match="finite") as error:
        washout_batch(baseline_parameters(), DT, force, rates)
    value = error.value.value
    assert error.value.field == "angular_velocity_rad_s[7, 2]" and isinstance(value, float) and math.isnan(value)


def test_batch_result_does_not_depend_on_the_chunk_size(monkeypatch: pytest.MonkeyPatch) -> None:
    import core.washout

    time_s = np.arange(5000) * DT
    force = np.stack([3 * np.sin(2.0 * time_s), 3 * np.cos(1.1 * time_s), 0.5 * np.sin(5 * time_s)], axis=1)
    rates = 0.3 * force[:, ::-1] / 3
    params = WashoutParameters(tilt_break_rad_s=3.0)
    whole = washout_batch(params, DT, force, rates)
    monkeypatch.setattr(core.washout, "BATCH_CHUNK_SAMPLES", 777)
    chunked = washout_batch(params, DT, force, rates)
    assert np.any(chunked.tilt_rate_limited)
    assert np.max(np.abs(chunked.acceleration - whole.acceleration)) < 1e-12
    assert np.array_equal(chunked.tilt_rate_limited, whole.tilt_rate_limited)


def test_head_lever_arm_compensation_changes_the_translational_channel_only() -> None:
    rng = np.random.default_rng(11)
    count = 5000
    time_s = np.arange(count) * DT
    force = np.stack([3 * np.sin(1.1 * time_s), 4 * np.sign(np.sin(0.8 * time_s)), rng.normal(0, 0.5, count)], axis=1)
    rates = np.stack([0.6 * np.sin(1.9 * time_s), rng.normal(0, 0.2, count), 0.8 * np.cos(0.5 * time_s)], axis=1)
    params = WashoutParameters(tilt_break_rad_s=2.0, tilt_rate_limit_rad_s=0.08, head_height_m=1.6)
    batch = washout_batch(params, DT, force, rates)
    assert np.any(batch.tilt_rate_limited)
    plain = washout_batch(replace(params, head_height_m=0.0), DT, force, rates)
    assert np.array_equal(plain.pose[:, 3:], batch.pose[:, 3:]) and not np.allclose(
        plain.pose[:, :3], batch.pose[:, :3]
    )


def test_head_compensation_delivers_the_tilt_onset_at_the_head() -> None:
    """§5 step, head 1.6 m up: at 0.1 s the tilt's angular acceleration cuts the felt cue to 0.36 m/s²;
    the compensated washout gives about twice that. (Over the whole run it does not help: the sustained
    part h·φ of the lever arm cannot pass the translational high-pass; docs/cueing.md.)"""
    from core.perception import head_specific_force

    force, rates = _signals(3.0)
    force[:, 1] = 0.2 * GRAVITY_M_S2
    felt = {}
    for height in (0.0, 1.6):
        trajectory = washout_batch(replace(paper_tilt_parameters(), head_height_m=height), DT, force, rates)
        pose, velocity, acceleration = trajectory.pose.T, trajectory.velocity.T, trajectory.acceleration.T
        felt[height] = head_specific_force(pose, velocity, acceleration, 1.6)[1, 100]
    assert felt[0.0] == pytest.approx(0.36, abs=0.02)
    assert felt[1.6] > 1.8 * felt[0.0]
    with pytest.raises(ParameterError, match="head_height_m"):
        WashoutParameters(head_height_m=-0.1)
