"""The simulated patient: body sizing, balance, falls, the harness, and streaming = batch."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.patient import (
    ParameterError,
    PatientParameters,
    Perturbation,
    SimulatedPatient,
    simulate,
    simulate_trial,
    support_motion,
)

PERIOD_S = 0.001


def healthy(**overrides: float) -> PatientParameters:
    return PatientParameters.preset("healthy", 70.0, 1.75, **overrides)


def impaired(**overrides: float) -> PatientParameters:
    return PatientParameters.preset("impaired", 70.0, 1.75, **overrides)


def test_body_is_sized_from_winters_proportions() -> None:
    params = healthy()
    assert params.com_height_above_ankle_m == pytest.approx((0.55 - 0.039) * 1.75)
    assert params.pendulum_mass_kg == pytest.approx(70.0 * (1 - 0.029))
    expected_inertia = params.pendulum_mass_kg * (params.com_height_above_ankle_m**2 + (0.24 * 1.75) ** 2)
    assert params.moment_of_inertia_kg_m2 == pytest.approx(expected_inertia)
    assert params.foot.heel_m + params.foot.toe_m == pytest.approx(0.152 * 1.75)


@pytest.mark.parametrize(
    ("field", "value"),
    [("body_mass_kg", 5.0), ("height_m", math.nan), ("proprioceptive_weight", 1.5), ("feedback_delay_s", -0.1)],
)
def test_invalid_parameters_are_refused_naming_the_field(field: str, value: float) -> None:
    with pytest.raises(ParameterError) as error:
        healthy(**{field: value}) if field not in ("body_mass_kg", "height_m") else PatientParameters(
            **{"body_mass_kg": 70.0, "height_m": 1.75, field: value}
        )
    assert error.value.field == field
    assert "must be" in str(error.value)


def test_unknown_preset_is_refused() -> None:
    with pytest.raises(ParameterError, match="preset"):
        PatientParameters.preset("athlete", 70.0, 1.75)


def test_parameters_round_trip_through_a_dict() -> None:
    params = impaired()
    assert PatientParameters.from_dict(params.to_dict()) == params
    with pytest.raises(ParameterError, match="unknown"):
        PatientParameters.from_dict({**params.to_dict(), "wings": 2})


def test_quiet_stance_carries_body_weight_on_two_feet_with_physiological_sway() -> None:
    params = healthy()
    _, trial = simulate_trial(params, [], 20.0, PERIOD_S, seed=3)
    assert math.isnan(trial.fall_onset_s)
    total = trial.plate_force_z_n.sum(axis=1)
    assert np.mean(total) == pytest.approx(params.body_weight_n, rel=0.01)
    assert np.mean(trial.plate_force_z_n[:, 0]) == pytest.approx(0.5 * params.body_weight_n, rel=0.05)
    sway_std_deg = np.degrees(trial.sway_angle_rad.std(axis=0))
    assert np.all((sway_std_deg > 0.05) & (sway_std_deg < 1.5))
    assert np.max(trial.harness_load_n) < 0.05 * params.body_weight_n  # the rope stays slack


def test_healthy_patient_stays_standing_through_mild_perturbations() -> None:
    mild = [
        Perturbation("translation", 2.0, 0.0, 1.0, 0.5),
        Perturbation("translation", 7.0, math.pi, 1.0, 0.5),
        Perturbation("tilt", 12.0, math.pi, math.radians(2.0), 0.5),
        Perturbation("tilt", 18.0, math.pi / 2, math.radians(2.0), 0.5),
    ]
    for seed in range(3):
        _, trial = simulate_trial(healthy(), mild, 24.0, PERIOD_S, seed=seed)
        assert math.isnan(trial.fall_onset_s), f"seed {seed}"
        assert not trial.fallen.any()


@pytest.mark.parametrize(
    "perturbation",
    [Perturbation("translation", 2.0, 0.0, 3.0, 0.5), Perturbation("tilt", 2.0, math.pi, math.radians(8.0), 0.5)],
)
def test_impaired_patient_falls_under_a_large_perturbation_and_the_harness_catches(perturbation: Perturbation) -> None:
    params = impaired(step_probability=0.0, grab_probability=0.0)  # no protective response: the rope catches
    _, trial = simulate_trial(params, [perturbation], 8.0, PERIOD_S, seed=1)
    assert perturbation.onset_s < trial.fall_onset_s < perturbation.onset_s + 3.0
    after = trial.time_s >= trial.fall_onset_s
    assert np.all(trial.fallen == after)  # the flag latches at the onset
    assert np.max(trial.harness_load_n[after]) > 0.3 * params.body_weight_n
    assert np.max(trial.harness_load_n[~after]) < 0.1 * params.body_weight_n
    # What the harness carries is taken off the plates.
    caught = np.argmax(trial.harness_load_n)
    assert trial.plate_force_z_n[caught].sum() < 0.9 * params.body_weight_n


def test_support_acceleration_tips_the_body_the_other_way() -> None:
    # Without the predictive feedforward (which cancels the inertial push) the equation's sign shows.
    quiet = healthy(sensory_noise_rad=0.0, motor_noise_per_mgh=0.0, acceleration_feedforward_gain=0.0)
    forward = Perturbation("translation", 1.0, 0.0, 1.0, 0.5)
    _, trial = simulate_trial(quiet, [forward], 1.2, PERIOD_S, 0)
    assert trial.sway_angle_rad[-1, 0] < -0.005  # the feet run forward, the body lags backward
    left = Perturbation("translation", 1.0, math.pi / 2, 1.5, 0.5)
    _, trial = simulate_trial(quiet, [left], 1.2, PERIOD_S, 0)
    assert trial.sway_angle_rad[-1, 1] < -0.005
    # Swaying to the right loads the right foot (index 0).
    assert trial.plate_force_z_n[-1, 0] > trial.plate_force_z_n[-1, 1] + 20.0


def test_tilt_enters_through_proprioception_and_passive_stiffness() -> None:
    quiet = {"sensory_noise_rad": 0.0, "motor_noise_per_mgh": 0.0, "plate_cop_noise_m": 0.0}
    toes_down = [Perturbation("tilt", 0.5, 0.0, math.radians(2.0), 0.5)]
    _, trial = simulate_trial(healthy(proprioceptive_weight=1.0, **quiet), toes_down, 1.5, PERIOD_S, 0)
    assert trial.sway_angle_rad[-1, 0] > math.radians(0.5)  # body follows the plate forward
    _, vestibular = simulate_trial(healthy(proprioceptive_weight=0.0, **quiet), toes_down, 1.5, PERIOD_S, 0)
    assert abs(vestibular.sway_angle_rad[-1, 0]) < trial.sway_angle_rad[-1, 0]  # graviception resists it


def test_cop_stays_on_the_feet_when_the_torque_saturates() -> None:
    params = healthy(plate_cop_noise_m=0.0)
    _, trial = simulate_trial(params, [Perturbation("translation", 1.0, 0.0, 3.0, 0.5)], 5.0, PERIOD_S, 2)
    loaded = trial.plate_force_z_n > 0.1 * params.body_weight_n
    cop_x = trial.plate_cop_m[..., 0][loaded]
    assert -params.foot.heel_m - 1e-9 <= cop_x.min() and cop_x.max() <= params.foot.toe_m + 1e-9
    # It reached an edge and stayed there: the torque saturated instead of the COP leaving the foot.
    at_edge = np.isclose(cop_x, -params.foot.heel_m, atol=1e-9) | np.isclose(cop_x, params.foot.toe_m, atol=1e-9)
    assert np.count_nonzero(at_edge) > 50


def test_measured_cop_never_leaves_the_sole_even_with_sensor_noise() -> None:
    """Issue 16 defect 4: a foot cannot push its COP outside its sole, whatever the noise of the plate."""
    params = impaired()
    hard = [Perturbation("translation", 1.0, 0.0, 3.0, 0.5), Perturbation("translation", 6.0, math.pi, 3.0, 0.5)]
    for seed in range(4):
        _, trial = simulate_trial(params, hard, 9.0, PERIOD_S, seed)
        cop = trial.plate_cop_m
        assert cop[..., 0].min() >= -params.foot.heel_m and cop[..., 0].max() <= params.foot.toe_m, seed
        assert np.abs(cop[..., 1]).max() <= params.foot.half_breadth_m, seed


def test_a_half_m_s2_training_sine_is_no_fall_for_a_healthy_patient() -> None:
    """0.5 m/s² at 0.5 Hz (the console's default cue) is ordinary training: no loss of balance, COP well inside."""
    time_s = np.arange(1, 20_001) * PERIOD_S
    acceleration = np.zeros((time_s.size, 3))
    acceleration[:, 0] = 0.5 * np.sin(2 * math.pi * 0.5 * time_s) * np.minimum(1.0, time_s / 3.0)
    for mass in (64.0, 120.0):
        params = PatientParameters.preset("healthy", mass, 1.75)
        trial = simulate(params, PERIOD_S, 5, acceleration, np.zeros((time_s.size, 2)), np.zeros((time_s.size, 3)))
        assert math.isnan(trial.fall_onset_s), mass
        assert np.degrees(np.abs(trial.sway_angle_rad[:, 0]).max()) < 2.0
        assert trial.plate_cop_m[..., 0].min() > -0.9 * params.foot.heel_m


@pytest.mark.parametrize(("mass_kg", "height_m"), [(55.0, 1.6), (70.0, 1.75), (120.0, 1.9)])
def test_an_impaired_patient_rides_the_slow_tilt_of_a_training_sine(mass_kg: float, height_m: float) -> None:
    """Issue 16 §11: the washout plays a 0.03 g, 0.25 Hz x-sine as a ±1.2° pitch, with ±0.09 m/s² left in the
    translation 74° ahead of it (measured on the kinematic backend). A patient with impaired balance trains
    at that; the former preset resonated at 0.31 Hz (sway 5× the tilt) and fell within 7 s."""
    time_s = np.arange(1, 30_001) * PERIOD_S
    omega = 2 * math.pi * 0.25
    ramp = np.where(time_s < 4.0, 0.5 * (1 - np.cos(math.pi * np.minimum(time_s, 4.0) / 4.0)), 1.0)
    tilt = np.zeros((time_s.size, 2))
    tilt[:, 1] = math.radians(1.2) * ramp * np.sin(omega * time_s)
    angular_velocity = np.zeros((time_s.size, 3))
    angular_velocity[:, 1] = np.gradient(tilt[:, 1], PERIOD_S)
    # The translation as a displacement, so that the support starts and stays at rest on average.
    displacement = 0.09 / omega**2 * ramp * np.sin(omega * time_s + math.radians(74.0))
    acceleration = np.zeros((time_s.size, 3))
    acceleration[:, 0] = np.gradient(np.gradient(displacement, PERIOD_S), PERIOD_S)
    for seed in range(3):
        params = PatientParameters.preset("impaired", mass_kg, height_m)
        trial = simulate(params, PERIOD_S, seed, acceleration, tilt, angular_velocity)
        assert math.isnan(trial.fall_onset_s), (seed, trial.fall_onset_s, trial.fall_response)
        assert np.degrees(np.abs(trial.sway_angle_rad[:, 0]).max()) < 4.0, seed


@pytest.mark.parametrize("response", ["step", "grab", "harness_catch"])
def test_a_loss_of_balance_is_a_step_a_grab_or_a_harness_catch(response: str) -> None:
    """Once the extrapolated COM leaves the feet the patient steps (a plate unloads), grabs the rail (the
    plates lose the hand's share) or is caught (the rope takes the weight, the body sags)."""
    shares = {"step": (1.0, 0.0), "grab": (0.0, 1.0), "harness_catch": (0.0, 0.0)}[response]
    params = impaired(step_probability=shares[0], grab_probability=shares[1])
    _, trial = simulate_trial(params, [Perturbation("translation", 1.0, 0.0, 3.0, 0.5)], 5.0, PERIOD_S, 3)
    assert trial.fall_response == response
    onset = trial.fall_onset_s
    assert 1.0 < onset < 2.5
    weight = params.body_weight_n
    before, after = trial.time_s < onset, trial.time_s > onset + 1.0
    assert np.max(trial.harness_load_n[before]) < 0.1 * weight
    if response == "step":
        unloaded = trial.plate_force_z_n.min(axis=1) < 0.05 * weight
        assert np.count_nonzero(unloaded & ~before) * PERIOD_S > 0.3  # a foot left its plate
        assert not unloaded[before].any()
    elif response == "grab":
        assert np.median(trial.plate_force_z_n[after].sum(axis=1)) < (1.0 - 0.8 * params.grab_load_fraction_bw) * weight
    else:
        assert np.max(trial.harness_load_n[after]) > 0.3 * weight
        assert trial.body_drop_m is not None and trial.body_drop_m.max() > 0.02


def test_streaming_steps_reproduce_the_batch_run_exactly() -> None:
    motion = support_motion([Perturbation("translation", 0.5, 0.3, 2.5, 0.5)], 3.0, PERIOD_S)
    batch = simulate(impaired(), PERIOD_S, 11, motion.acceleration_m_s2, motion.tilt_rad, motion.angular_velocity_rad_s)
    patient = SimulatedPatient(impaired(), PERIOD_S, seed=11)
    for index in range(len(motion.time_s)):
        sample = patient.step(
            motion.acceleration_m_s2[index], motion.tilt_rad[index], motion.angular_velocity_rad_s[index]
        )
        assert np.array_equal(sample.plate_force_z_n, batch.plate_force_z_n[index])
        assert np.array_equal(sample.plate_cop_m, batch.plate_cop_m[index])
        assert sample.harness_load_n == batch.harness_load_n[index]
        assert sample.fallen == batch.fallen[index]
    assert patient.fall_onset_s == batch.fall_onset_s
    # Per-tick: the same sample object and buffers every step, nothing new allocated for the caller.
    first = patient.step(np.zeros(3), np.zeros(2), np.zeros(3))
    forces = first.plate_force_z_n
    assert patient.step(np.zeros(3), np.zeros(2), np.zeros(3)) is first and first.plate_force_z_n is forces
    patient.reset()
    assert not patient.fallen and math.isnan(patient.fall_onset_s)


def test_seeds_are_reproducible_and_distinct() -> None:
    motion = support_motion([], 1.0, PERIOD_S)
    runs = [
        simulate(healthy(), PERIOD_S, seed, motion.acceleration_m_s2, motion.tilt_rad, motion.angular_velocity_rad_s)
        for seed in (4, 4, 5)
    ]
    assert np.array_equal(runs[0].plate_cop_m, runs[1].plate_cop_m)
    assert not np.array_equal(runs[0].plate_cop_m, runs[2].plate_cop_m)


def test_a_coarser_period_is_substepped_to_the_same_behaviour() -> None:
    big = [Perturbation("translation", 1.0, 0.0, 3.0, 0.5)]
    fine = simulate_trial(impaired(), big, 5.0, 0.001, 0)[1]
    coarse = simulate_trial(impaired(), big, 5.0, 0.004, 0)[1]
    assert coarse.fall_onset_s == pytest.approx(fine.fall_onset_s, abs=0.1)


def test_bad_inputs_are_refused() -> None:
    with pytest.raises(ParameterError, match="sample_period_s"):
        SimulatedPatient(healthy(), 0.0)
    patient = SimulatedPatient(healthy(), PERIOD_S)
    with pytest.raises(ParameterError, match="support_acceleration_m_s2"):
        patient.step(np.zeros(2), np.zeros(2), np.zeros(3))
    with pytest.raises(ParameterError, match="support_tilt_rad"):
        simulate(healthy(), PERIOD_S, 0, np.zeros((5, 3)), np.zeros((4, 2)), np.zeros((5, 3)))
    with pytest.raises(ParameterError, match="magnitude"):
        Perturbation("tilt", 1.0, 0.0, math.radians(40.0), 0.5)
    with pytest.raises(ParameterError, match="kind"):
        Perturbation("shove", 1.0, 0.0, 1.0, 0.5)


def test_support_motion_shapes_a_tilt_pulse_that_returns_to_level() -> None:
    motion = support_motion([Perturbation("tilt", 1.0, math.pi / 2, 0.1, 0.5)], 4.0, PERIOD_S)
    roll = motion.tilt_rad[:, 0]
    assert roll.min() == pytest.approx(-0.1)  # tipping toward +y is negative roll
    assert roll[-1] == 0.0
    # The angular velocity integrates to the tilt.
    integrated = np.cumsum(motion.angular_velocity_rad_s[:, 0]) * PERIOD_S
    assert np.max(np.abs(integrated - roll)) < 2e-3


def test_the_feedforward_torque_does_not_follow_a_structural_vibration() -> None:
    """Muscles cannot make torque at 90 Hz. The feedforward that cancels the support's inertial push went
    straight from the sensed acceleration to the ankle torque, so the COP followed a platform vibration; on
    the MuJoCo backend that closed a loop with the structure and a 120 kg patient rang at 89 Hz."""
    params = healthy(plate_cop_noise_m=0.0, sensory_noise_rad=0.0, motor_noise_per_mgh=0.0)
    time_s = np.arange(1, 4001) * PERIOD_S
    acceleration = np.zeros((time_s.size, 3))
    acceleration[:, 0] = 1.0 * np.sin(2 * math.pi * 90.0 * time_s)  # m/s², as the finite-differenced plate
    trial = simulate(params, PERIOD_S, 0, acceleration, np.zeros((time_s.size, 2)), np.zeros((time_s.size, 3)))
    cop_x = trial.plate_cop_m[2000:, 0, 0]
    # A torque following m·h·a would swing the COP by h·a/g ≈ ±95 mm (to the edges of the foot).
    assert np.ptp(cop_x) < 0.015, f"COP swings {1e3 * np.ptp(cop_x):.0f} mm peak to peak"
