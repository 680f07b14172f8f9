"""Fall detectors on synthetic signals (edges, noise, spikes), streaming = batch, and scoring."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.falls import (
    ANY_DETECTOR,
    COP_OUTSIDE_BASE,
    FOOT_UNLOADED,
    FUSED,
    HARNESS_LOAD,
    CopOutsideBaseConfig,
    FallDetectorConfig,
    FallEvent,
    FallMonitor,
    FootUnloadedConfig,
    FusedDetector,
    HarnessLoadConfig,
    LabelledLog,
    MatchingWindow,
    SessionDetections,
    detect_falls,
    roc_curve,
    samples_for,
    score_detector,
    tune_fused,
)
from core.patient import GRAVITY_M_S2, ParameterError, PatientParameters, Perturbation, simulate, simulate_trial

PERIOD_S = 0.001
MASS_KG = 70.0
WEIGHT_N = MASS_KG * GRAVITY_M_S2


def quiet_signals(count: int) -> dict[str, np.ndarray]:
    """Standing still: half the weight on each plate, COP under the ankles, slack harness."""
    return {
        "time_s": np.arange(count) * PERIOD_S,
        "plate_force_z_n": np.full((count, 2), WEIGHT_N / 2),
        "plate_cop_m": np.zeros((count, 2, 2)),
        "harness_load_n": np.zeros(count),
    }


def config(**sections: object) -> FallDetectorConfig:
    return FallDetectorConfig(body_mass_kg=MASS_KG, **sections)  # type: ignore[arg-type]


def batch(cfg: FallDetectorConfig, signals: dict[str, np.ndarray]) -> list[FallEvent]:
    return detect_falls(cfg, PERIOD_S, **signals)


def streamed(cfg: FallDetectorConfig, signals: dict[str, np.ndarray]) -> list[FallEvent]:
    monitor = FallMonitor(cfg, PERIOD_S)
    for index, time_s in enumerate(signals["time_s"]):
        monitor.step(
            float(time_s),
            signals["plate_force_z_n"][index],
            signals["plate_cop_m"][index],
            float(signals["harness_load_n"][index]),
        )
    return monitor.events


def both(cfg: FallDetectorConfig, signals: dict[str, np.ndarray]) -> list[FallEvent]:
    """Run the batch and the streaming forms; they must agree event for event."""
    from_batch, from_stream = batch(cfg, signals), streamed(cfg, signals)
    assert from_batch == from_stream
    return from_batch


# --- harness load --------------------------------------------------------------------------------------


def test_harness_threshold_defaults_to_thirty_percent_body_weight() -> None:
    assert HarnessLoadConfig().threshold_fraction_bw == 0.30


def test_harness_load_at_exactly_the_threshold_does_not_fire_but_just_above_does() -> None:
    signals = quiet_signals(1000)
    signals["harness_load_n"][100:400] = 0.3 * WEIGHT_N
    assert both(config(), signals) == []
    signals["harness_load_n"][100:400] = 0.3 * WEIGHT_N + 0.01
    (event,) = both(config(), signals)
    required = samples_for(0.05, PERIOD_S)
    assert (event.detector, event.tick) == (HARNESS_LOAD, 100 + required - 1)
    assert event.onset_s == pytest.approx(0.1)
    assert event.detected_s == pytest.approx(0.1 + (required - 1) * PERIOD_S)
    assert event.values["threshold_n"] == pytest.approx(0.3 * WEIGHT_N)


def test_a_harness_spike_shorter_than_the_minimum_duration_does_not_fire() -> None:
    signals = quiet_signals(1000)
    required = samples_for(0.05, PERIOD_S)
    signals["harness_load_n"][200 : 200 + required - 1] = WEIGHT_N  # a rope snatch, one sample short
    assert both(config(), signals) == []
    signals["harness_load_n"][200 : 200 + required] = WEIGHT_N
    assert len(both(config(), signals)) == 1


def test_noise_below_the_harness_threshold_never_fires_and_each_run_fires_once() -> None:
    rng = np.random.default_rng(0)
    signals = quiet_signals(5000)
    signals["harness_load_n"] = np.abs(rng.normal(0.0, 0.08 * WEIGHT_N, 5000))  # 3.75 σ below 30 % BW
    signals["harness_load_n"][2000:3000] = 0.6 * WEIGHT_N
    signals["harness_load_n"][4000:4200] = 0.6 * WEIGHT_N
    events = both(config(), signals)
    assert [e.onset_s for e in events] == pytest.approx([2.0, 4.0])


# --- centre of pressure ----------------------------------------------------------------------------------


def test_cop_inside_the_margin_is_quiet_and_beyond_it_fires_on_a_loaded_plate() -> None:
    cop_config = CopOutsideBaseConfig(x_min_m=-0.06, x_max_m=0.2, y_min_m=-0.05, y_max_m=0.05, margin_m=0.01)
    signals = quiet_signals(1000)
    signals["plate_cop_m"][:, 1, 0] = 0.19  # exactly on the margin: still inside
    assert both(config(cop=cop_config), signals) == []
    signals["plate_cop_m"][300:, 1, 0] = 0.1901
    (event,) = both(config(cop=cop_config), signals)
    assert event.detector == COP_OUTSIDE_BASE
    assert event.onset_s == pytest.approx(0.3)
    assert event.values["feet"] == ["left"]


def test_cop_on_an_unloaded_plate_is_ignored() -> None:
    signals = quiet_signals(1000)
    signals["plate_force_z_n"][:, 0] = 0.05 * WEIGHT_N  # below the 10 % BW trust level
    signals["plate_cop_m"][:, 0, 1] = 0.3  # the right plate's COP is meaningless
    assert both(config(unload=FootUnloadedConfig(enabled=False)), signals) == []


def test_a_short_cop_excursion_does_not_fire() -> None:
    signals = quiet_signals(1000)
    required = samples_for(0.1, PERIOD_S)
    signals["plate_cop_m"][500 : 500 + required - 1, 0, 0] = -0.2
    assert both(config(), signals) == []


def test_cop_footprint_follows_the_patients_feet() -> None:
    patient = PatientParameters.preset("healthy", MASS_KG, 1.8)
    cop = FallDetectorConfig.for_patient(MASS_KG, 1.8).cop
    assert (cop.x_min_m, cop.x_max_m) == pytest.approx((-patient.foot.heel_m, patient.foot.toe_m))


# --- foot unloaded ---------------------------------------------------------------------------------------


def test_a_foot_losing_its_load_fires_after_the_minimum_time() -> None:
    signals = quiet_signals(2000)
    required = samples_for(0.2, PERIOD_S)
    signals["plate_force_z_n"][100 : 100 + required - 1, 0] = 0.0  # a short unweighting: quiet
    signals["plate_force_z_n"][1000:, 1] = 0.049 * WEIGHT_N
    (event,) = both(config(), signals)
    assert event.detector == FOOT_UNLOADED
    assert event.values["feet"] == ["left"]
    assert event.tick == 1000 + required - 1


def test_monitor_latches_returns_no_new_object_on_quiet_ticks_and_resets() -> None:
    monitor = FallMonitor(config(), PERIOD_S)
    forces, cops = np.full(2, WEIGHT_N / 2), np.zeros((2, 2))
    quiet = monitor.step(0.0, forces, cops, 0.0)
    assert quiet == () and quiet is monitor.step(0.001, forces, cops, 0.0)
    fired = [monitor.step(0.002 + k * PERIOD_S, forces, cops, WEIGHT_N) for k in range(100)]
    assert sum(len(f) for f in fired) == 1 and monitor.fallen
    assert monitor.events[0].to_dict()["kind"] == "fall"
    monitor.reset()
    assert not monitor.fallen and monitor.events == [] and monitor.tick == 0


def test_streaming_and_batch_agree_on_noisy_random_signals() -> None:
    rng = np.random.default_rng(42)
    count = 4000
    signals = {
        "time_s": np.arange(count) * PERIOD_S,
        "plate_force_z_n": WEIGHT_N / 2 + rng.normal(0, 0.3 * WEIGHT_N, (count, 2)),
        "plate_cop_m": rng.normal(0, 0.08, (count, 2, 2)),
        "harness_load_n": np.abs(rng.normal(0, 0.25 * WEIGHT_N, count)),
    }
    short = config(
        harness=HarnessLoadConfig(min_duration_s=0.002),
        cop=CopOutsideBaseConfig(min_duration_s=0.003),
        unload=FootUnloadedConfig(threshold_fraction_bw=0.2, min_duration_s=0.002),
    )
    events = both(short, signals)
    assert {e.detector for e in events} == {HARNESS_LOAD, COP_OUTSIDE_BASE, FOOT_UNLOADED}


def test_detectors_catch_a_simulated_fall_after_it_starts() -> None:
    # No protective response: the harness catches the patient.
    params = PatientParameters.preset("impaired", MASS_KG, 1.75, step_probability=0.0, grab_probability=0.0)
    _, trial = simulate_trial(params, [Perturbation("translation", 2.0, 0.0, 3.0, 0.5)], 6.0, PERIOD_S, 1)
    events = detect_falls(
        FallDetectorConfig.for_patient(MASS_KG, 1.75),
        PERIOD_S,
        trial.time_s,
        trial.plate_force_z_n,
        trial.plate_cop_m,
        trial.harness_load_n,
    )
    harness = [e for e in events if e.detector == HARNESS_LOAD]
    assert harness and trial.fall_onset_s < harness[0].detected_s < trial.fall_onset_s + 2.0
    assert all(e.detected_s > 2.0 for e in events)  # nothing before the perturbation


# --- configuration ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("build", "field"),
    [
        (lambda: HarnessLoadConfig(threshold_fraction_bw=0.0), "harness.threshold_fraction_bw"),
        (lambda: HarnessLoadConfig(min_duration_s=-1.0), "harness.min_duration_s"),
        (lambda: CopOutsideBaseConfig(x_min_m=0.3, x_max_m=0.2), "cop.x_max_m"),
        (lambda: CopOutsideBaseConfig(margin_m=0.05), "cop.margin_m"),
        (lambda: FootUnloadedConfig(threshold_fraction_bw=math.nan), "unload.threshold_fraction_bw"),
        (lambda: FallDetectorConfig(body_mass_kg=0.0), "body_mass_kg"),
    ],
)
def test_invalid_settings_name_the_field_value_and_limit(build: object, field: str) -> None:
    with pytest.raises(ParameterError) as error:
        build()  # type: ignore[operator]
    assert error.value.field == field
    assert error.value.limit


def test_configuration_round_trips_and_refuses_unknown_keys() -> None:
    original = FallDetectorConfig.for_patient(MASS_KG, 1.7)
    assert FallDetectorConfig.from_dict(original.to_dict()) == original
    with pytest.raises(ParameterError, match=r"harness\.threshold"):
        FallDetectorConfig.from_dict({"body_mass_kg": MASS_KG, "harness": {"threshold": 0.3}})


def test_signals_of_the_wrong_shape_are_refused() -> None:
    signals = quiet_signals(10)
    signals["plate_cop_m"] = np.zeros((10, 2))
    with pytest.raises(ParameterError, match="plate_cop_m"):
        batch(config(), signals)


# --- scoring ---------------------------------------------------------------------------------------------


def event(detector: str, detected_s: float) -> FallEvent:
    return FallEvent(detector, detected_s - 0.05, detected_s, 0, {})


def test_scoring_counts_hits_latency_duplicates_and_false_alarms() -> None:
    sessions = [
        SessionDetections(
            "a",
            1800.0,
            (100.0,),
            (
                event(HARNESS_LOAD, 100.3),
                event(HARNESS_LOAD, 101.0),
                event(HARNESS_LOAD, 105.0),
                event(HARNESS_LOAD, 500.0),
            ),
        ),
        SessionDetections("b", 1800.0, (50.0,), (event(COP_OUTSIDE_BASE, 49.5), event(HARNESS_LOAD, 53.0))),
    ]
    harness = score_detector(sessions, HARNESS_LOAD, MatchingWindow(before_s=1.0, after_s=2.0))
    # 100.3 hits (latency 0.3), 101.0 a duplicate, 105.0 a post-fall rebound, 500 a false alarm; 53.0 is
    # 3 s late: a miss, and a post-fall detection rather than a false alarm.
    assert (harness.falls, harness.detected, harness.false_alarms) == (2, 1, 1)
    assert harness.sensitivity == 0.5
    assert harness.latencies_s == pytest.approx((0.3,))
    assert harness.false_alarms_per_hour == pytest.approx(1.0)
    combined = score_detector(sessions, ANY_DETECTOR)
    assert combined.detected == 2
    assert sorted(combined.latencies_s) == pytest.approx([-0.5, 0.3])
    assert combined.to_dict()["latency_median_s"] == pytest.approx(-0.1)


def test_scoring_without_falls_or_detections_is_defined() -> None:
    score = score_detector([SessionDetections("quiet", 3600.0, (), ())], HARNESS_LOAD)
    assert math.isnan(score.sensitivity) and score.false_alarms_per_hour == 0.0
    assert math.isnan(score.latency_percentile_s(50))


# --- the fused detector (issue 16 defect 5) -------------------------------------------------------------


def fused_only(mass_kg: float = MASS_KG, height_m: float = 1.75) -> FallDetectorConfig:
    return FallDetectorConfig.for_patient(mass_kg, height_m)


def run_detectors(config: FallDetectorConfig, trial: object, support_az: np.ndarray | None = None) -> list:
    return detect_falls(
        config,
        PERIOD_S,
        trial.time_s,  # type: ignore[attr-defined]
        trial.plate_force_z_n,  # type: ignore[attr-defined]
        trial.plate_cop_m,  # type: ignore[attr-defined]
        trial.harness_load_n,  # type: ignore[attr-defined]
        support_az,
    )


@pytest.mark.parametrize("response", ["step", "grab", "harness_catch"])
def test_the_fused_detector_catches_a_step_a_grab_and_a_harness_catch(response: str) -> None:
    """The original detectors missed most of these (sensitivity 0.67; foot-unloaded never fired)."""
    shares = {"step": (1.0, 0.0), "grab": (0.0, 1.0), "harness_catch": (0.0, 0.0)}[response]
    params = PatientParameters.preset("impaired", MASS_KG, 1.75, step_probability=shares[0], grab_probability=shares[1])
    _, trial = simulate_trial(params, [Perturbation("translation", 2.0, 0.0, 2.5, 0.5)], 7.0, PERIOD_S, 4)
    assert trial.fall_response == response
    events = [e for e in run_detectors(fused_only(), trial) if e.detector == FUSED]
    assert events, f"{response}: the fused detector never fired"
    assert trial.fall_onset_s - 1.0 <= events[0].detected_s <= trial.fall_onset_s + 2.0
    assert events[0].values["score"] >= events[0].values["threshold"]
    assert set(events[0].values["evidence"]) == {"harness", "edge", "drop", "unload", "foot"}


def test_the_fused_detector_stays_quiet_through_hard_recoveries_and_heave() -> None:
    """A healthy patient recovering from 1 m/s² pulses (COP near the heel/toe) is no fall; nor is a heave
    cue, whose vertical support acceleration the detector takes out of the body-drop estimate."""
    pulses = [Perturbation("translation", 2.0 + 6.0 * k, k * math.pi / 2, 1.0, 0.5) for k in range(4)]
    for seed in range(3):
        _, trial = simulate_trial(PatientParameters.preset("healthy", MASS_KG, 1.75), pulses, 28.0, PERIOD_S, seed)
        assert math.isnan(trial.fall_onset_s)
        assert not run_detectors(fused_only(), trial), seed
    time_s = np.arange(1, 20_001) * PERIOD_S
    heave = np.zeros((time_s.size, 3))
    heave[:, 2] = 1.0 * np.sin(2 * math.pi * 1.0 * time_s)  # ±2.5 cm: inside the harness slack
    params = PatientParameters.preset("healthy", MASS_KG, 1.75)
    trial = simulate(params, PERIOD_S, 1, heave, np.zeros((time_s.size, 2)), np.zeros((time_s.size, 3)))
    assert math.isnan(trial.fall_onset_s)
    assert not run_detectors(fused_only(), trial, heave[:, 2])
    fused = FusedDetector(fused_only(), PERIOD_S)
    with_heave, _ = fused.scores(trial.plate_force_z_n, trial.plate_cop_m, trial.harness_load_n, heave[:, 2])
    without, _ = fused.scores(trial.plate_force_z_n, trial.plate_cop_m, trial.harness_load_n)
    assert with_heave.max() < 0.5 * without.max()  # the load swing of the heave is not a body drop


def test_the_fused_detector_streams_the_events_of_the_batch_form() -> None:
    params = PatientParameters.preset("impaired", MASS_KG, 1.75, step_probability=0.0, grab_probability=1.0)
    _, trial = simulate_trial(params, [Perturbation("translation", 1.0, 0.0, 2.5, 0.5)], 5.0, PERIOD_S, 2)
    config = fused_only()
    batch = [e for e in run_detectors(config, trial) if e.detector == FUSED]
    monitor = FallMonitor(config, PERIOD_S)
    streamed = []
    for n in range(len(trial.time_s)):
        fired = monitor.step(trial.time_s[n], trial.plate_force_z_n[n], trial.plate_cop_m[n], trial.harness_load_n[n])
        streamed += [e for e in fired if e.detector == FUSED]
    assert batch and [(e.tick, e.onset_s, e.detected_s) for e in streamed] == [
        (e.tick, e.onset_s, e.detected_s) for e in batch
    ]
    assert streamed[0].values == batch[0].values


def test_invalid_fused_settings_are_refused_naming_the_field() -> None:
    with pytest.raises(ParameterError) as error:
        FallDetectorConfig.from_dict({"body_mass_kg": MASS_KG, "fused": {"threshold": 0.0}})
    assert error.value.field == "fused.threshold"
    with pytest.raises(ParameterError, match=r"fused\.wings"):
        FallDetectorConfig.from_dict({"body_mass_kg": MASS_KG, "fused": {"wings": 1}})


def test_roc_curves_and_tuning_on_labelled_logs() -> None:
    logs = []
    for index, (preset, magnitude) in enumerate(
        [("impaired", 3.0), ("healthy", 1.0), ("impaired", 3.0), ("healthy", 0.8)]
    ):
        params = PatientParameters.preset(preset, MASS_KG, 1.75)
        _, trial = simulate_trial(params, [Perturbation("translation", 2.0, 0.0, magnitude, 0.5)], 8.0, PERIOD_S, index)
        onsets = () if math.isnan(trial.fall_onset_s) else (trial.fall_onset_s,)
        logs.append(
            LabelledLog(
                f"s{index}",
                fused_only(),
                PERIOD_S,
                trial.time_s,
                trial.plate_force_z_n,
                trial.plate_cop_m,
                trial.harness_load_n,
                None,
                onsets,
            )
        )
    assert sum(len(log.fall_onsets_s) for log in logs) == 2
    curve = roc_curve(logs, FUSED)
    assert [p.threshold for p in curve] == sorted(p.threshold for p in curve)
    assert curve[0].sensitivity == 1.0 and curve[-1].sensitivity <= curve[0].sensitivity
    grid = {
        "weight_edge": (0.0, 0.5),
        "weight_foot": (0.5,),
        "drop_reference_m": (0.07,),
        "unload_reference_fraction": (0.3,),
    }
    result = tune_fused(logs, grid=grid)
    assert result.combinations == 2 and result.training.sensitivity == 1.0
    assert result.training.false_alarms_per_hour <= 1.0 and set(result.settings) == {*grid, "threshold"}
    with pytest.raises(ParameterError, match="detector"):
        roc_curve(logs, "crystal_ball")
