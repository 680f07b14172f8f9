"""Motion-cue generators: the paper's signals, streaming = batch, seeded randomness, refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.cues import CSV_FORCE_COLUMNS, CueSpecError, cue_from_spec, validate_cue_spec

PERIOD_S = 0.001

SPECS = [
    {"kind": "square_wave", "axis": "x", "amplitude_m_s2": 2.0, "period_s": 2.0},
    {"kind": "step", "axis": "z", "initial_m_s2": 5.0, "final_m_s2": 0.5, "step_time_s": 0.1},
    {"kind": "sine", "axis": "pitch", "amplitude_rad_s": 0.2, "frequency_hz": 0.5, "phase_rad": 0.3},
    {
        "kind": "multisine",
        "components": [
            {"axis": "y", "amplitude_m_s2": 0.4, "frequency_hz": 0.3},
            {"axis": "y", "amplitude_m_s2": 0.2, "frequency_hz": 1.1},
            {"axis": "roll", "amplitude_rad_s": 0.1, "frequency_hz": 0.7},
        ],
    },
    {"kind": "gait", "cadence_steps_per_min": 100, "vertical_amplitude_m_s2": 0.8, "lateral_amplitude_m_s2": 0.3},
    {
        "kind": "perturbations",
        "translation_m_s2": 1.5,
        "tilt_rate_rad_s": 0.3,
        "interval_min_s": 1.0,
        "interval_max_s": 2.0,
    },
    {
        "kind": "csv_replay",
        "csv": "time_s,specific_force_x_m_s2,specific_force_y_m_s2,specific_force_z_m_s2\n0,0,0,0\n1,1,0,0\n2,0,-1,0\n",
    },
]


@pytest.mark.parametrize("spec", SPECS, ids=[s["kind"] for s in SPECS])
def test_streaming_gives_the_same_numbers_as_batch(spec: dict) -> None:
    generator = cue_from_spec(spec, PERIOD_S, seed=7)
    force, angular = generator.generate(3.0)
    streamed = np.array([np.concatenate(generator.step()) for _ in range(len(force))])
    assert len(force) == 3000
    np.testing.assert_array_equal(streamed, np.hstack([force, angular]))
    assert np.any(streamed != 0.0)


def test_paper_square_wave_alternates_every_second() -> None:
    force, angular = cue_from_spec(SPECS[0], PERIOD_S).generate(10.0)  # paper §4.2: period 2 s, 2 m/s², 10 s
    assert np.all(force[:1000, 0] == 2.0) and np.all(force[1000:2000, 0] == -2.0)
    assert np.all(force[:, 1:] == 0.0) and np.all(angular == 0.0)
    assert np.mean(force[:, 0]) == pytest.approx(0.0)


def test_paper_step_changes_at_a_tenth_of_a_second() -> None:
    force, _ = cue_from_spec(SPECS[1], PERIOD_S).generate(0.3)  # paper §3.2: 5 → 0.5 m/s² at 0.1 s, along +Z
    assert np.all(force[:100, 2] == 5.0) and np.all(force[100:, 2] == 0.5)


def test_step_with_an_end_returns_to_its_initial_level() -> None:
    spec = {"kind": "step", "axis": "y", "final_m_s2": 0.2 * 9.80665, "step_time_s": 1.0, "end_time_s": 11.0}
    force, _ = cue_from_spec(spec, PERIOD_S).generate(12.0)  # paper §4.3: 0.2 g for 10 s
    assert force[999, 1] == 0.0 and force[1000, 1] == pytest.approx(1.96133) and force[11000, 1] == 0.0


def test_gait_runs_vertical_at_step_and_lateral_at_stride_frequency() -> None:
    force, _ = cue_from_spec(SPECS[4], PERIOD_S).generate(12.0)
    spectrum_z = np.abs(np.fft.rfft(force[:, 2]))
    spectrum_y = np.abs(np.fft.rfft(force[:, 1]))
    frequencies = np.fft.rfftfreq(len(force), PERIOD_S)
    assert frequencies[np.argmax(spectrum_z)] == pytest.approx(100 / 60, abs=0.1)
    assert frequencies[np.argmax(spectrum_y)] == pytest.approx(50 / 60, abs=0.1)


def test_perturbations_are_reproducible_from_the_seed_and_vary_with_it() -> None:
    spec = SPECS[5]
    first, _ = cue_from_spec(spec, PERIOD_S, seed=3).generate(30.0)
    again, _ = cue_from_spec(spec, PERIOD_S, seed=3).generate(30.0)
    other, _ = cue_from_spec(spec, PERIOD_S, seed=4).generate(30.0)
    np.testing.assert_array_equal(first, again)
    assert not np.array_equal(first, other)


def test_perturbation_pulses_respect_magnitude_intervals_and_net_zero_velocity() -> None:
    spec = {
        "kind": "perturbations",
        "translation_m_s2": 1.5,
        "pulse_duration_s": 0.5,
        "interval_min_s": 2.0,
        "interval_max_s": 4.0,
    }
    generator = cue_from_spec(spec, PERIOD_S, seed=11)
    force, angular = generator.generate(60.0)
    magnitude = np.hypot(force[:, 0], force[:, 1])
    assert magnitude.max() == pytest.approx(1.5, rel=1e-3)
    assert np.all(angular == 0.0) and np.all(force[:, 2] == 0.0)
    onsets = generator.onsets_s[generator.onsets_s < 59.0]
    gaps = np.diff(onsets)
    assert len(onsets) >= 12 and gaps.min() >= 2.0 and gaps.max() <= 4.0
    directions = generator.directions_rad[: len(onsets)]
    assert np.ptp(np.mod(directions, 2 * math.pi)) > math.pi / 2  # directions really vary
    # Each pulse is one sine period: the support ends each pulse at rest.
    assert np.abs(np.sum(force, axis=0) * PERIOD_S).max() < 1e-6


def test_csv_replay_interpolates_and_ends_at_zero() -> None:
    force, angular = cue_from_spec(SPECS[6], PERIOD_S).generate(3.0)
    assert force[500, 0] == pytest.approx(0.5) and force[1500, 1] == pytest.approx(-0.5)
    assert np.all(force[2001:] == 0.0) and np.all(angular == 0.0)


@pytest.mark.parametrize(
    ("spec", "field"),
    [
        ({"kind": "wobble"}, "kind"),
        ({"kind": "sine", "axis": "w", "amplitude_m_s2": 1.0, "frequency_hz": 1.0}, "axis"),
        ({"kind": "sine", "axis": "x", "amplitude_rad_s": 1.0, "frequency_hz": 1.0}, "amplitude_rad_s"),
        ({"kind": "sine", "axis": "x", "amplitude_m_s2": 1.0, "frequency_hz": 9.0}, "frequency_hz"),
        ({"kind": "sine", "axis": "x", "amplitude_m_s2": float("nan"), "frequency_hz": 1.0}, "amplitude_m_s2"),
        ({"kind": "square_wave", "axis": "x", "amplitude_m_s2": 50.0, "period_s": 2.0}, "amplitude_m_s2"),
        ({"kind": "multisine", "components": [{"axis": "x", "amplitude_m_s2": 1.0}]}, "components[0].frequency_hz"),
        ({"kind": "gait", "cadence_steps_per_min": 400, "vertical_amplitude_m_s2": 1.0}, "cadence_steps_per_min"),
        ({"kind": "perturbations", "translation_m_s2": 1.0, "interval_min_s": 0.1}, "interval_min_s"),
        ({"kind": "step", "axis": "y", "final_m_s2": 1.0, "step_time_s": 5.0, "end_time_s": 2.0}, "end_time_s"),
        ({"kind": "sine", "axis": "x", "amplitude_m_s2": 1.0, "frequency_hz": 1.0, "colour": "red"}, "colour"),
    ],
)
def test_invalid_specs_are_refused_naming_the_field(spec: dict, field: str) -> None:
    with pytest.raises(CueSpecError) as refused:
        validate_cue_spec(spec)
    assert refused.value.field == field


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("time_s,specific_force_x_m_s2\n0,1\n1,2\n", "csv.header"),
        ("time_s," + ",".join(CSV_FORCE_COLUMNS) + "\n0,0,0,0\n", "csv.rows"),
        ("time_s," + ",".join(CSV_FORCE_COLUMNS) + "\n0,0,0,0\n1,0,nan,0\n", "csv[2].specific_force_y_m_s2"),
        ("time_s," + ",".join(CSV_FORCE_COLUMNS) + "\n0,0,0,0\n0,0,0,0\n", "csv[2].time_s"),
        ("time_s," + ",".join(CSV_FORCE_COLUMNS) + "\n0,0,0,0\n1,0,0,99\n", "csv[2].specific_force_z_m_s2"),
        ("time_s," + ",".join(CSV_FORCE_COLUMNS) + "\n0,0,0,0\n1,0,zero,0\n", "csv"),
    ],
)
def test_invalid_csv_uploads_are_refused(text: str, field: str) -> None:
    with pytest.raises(CueSpecError) as refused:
        validate_cue_spec({"kind": "csv_replay", "csv": text})
    assert refused.value.field == field
