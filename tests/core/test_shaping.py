"""Command shaping keeps the first natural frequency (9.7559 Hz) out of the platform commands."""

from __future__ import annotations

import control
import numpy as np
import pytest

from core.shaping import (
    FIRST_MODE_HZ,
    CommandShaper,
    ParameterError,
    ShapingParameters,
    tustin_first_order,
    tustin_second_order,
)

DT = 0.001


def _amplitude_ratio(shaper: CommandShaper, frequency_hz: float) -> float:
    time_s = np.arange(int(8.0 / DT)) * DT
    poses = np.zeros((len(time_s), 6))
    poses[:, 1] = 0.01 * np.sin(2 * np.pi * frequency_hz * time_s)
    shaped = shaper.shape_batch(poses)[:, 1]
    settled = time_s > 4.0
    return float(np.max(np.abs(shaped[settled])) / 0.01)


def test_shaping_is_on_by_default_and_attenuates_the_first_mode() -> None:
    params = ShapingParameters()
    assert params.enabled
    shaper = CommandShaper(params, DT)
    ratio = _amplitude_ratio(shaper, FIRST_MODE_HZ)
    assert ratio < 10 ** (-params.required_attenuation_db / 20)
    assert ratio == pytest.approx(10 ** (-shaper.attenuation_db([FIRST_MODE_HZ])[0] / 20), rel=0.02)
    assert _amplitude_ratio(shaper, 0.3) > 0.98  # cue content passes


def test_notch_shaping_also_attenuates_the_first_mode() -> None:
    shaper = CommandShaper(ShapingParameters(kind="notch"), DT)
    assert _amplitude_ratio(shaper, FIRST_MODE_HZ) < 0.02
    assert np.all(shaper.attenuation_db(FIRST_MODE_HZ * np.array([0.9, 1.0, 1.1])) >= 20.0)


def test_a_filter_that_leaves_the_mode_exposed_is_refused() -> None:
    with pytest.raises(ParameterError) as error:
        CommandShaper(ShapingParameters(lowpass_cutoff_hz=8.0), DT)
    assert error.value.field == "lowpass_cutoff_hz"
    assert "required_attenuation_db" in str(error.value)
    with pytest.raises(ParameterError, match="notch_quality"):
        ShapingParameters(kind="notch", notch_quality=0.0)
    with pytest.raises(ParameterError, match="kind"):
        ShapingParameters(kind="bandpass")


def test_parameters_round_trip_and_reject_unknown_keys() -> None:
    params = ShapingParameters(kind="notch", notch_quality=0.3)
    assert ShapingParameters.from_dict(params.to_dict()) == params
    with pytest.raises(ParameterError, match="cutoff"):
        ShapingParameters.from_dict({"cutoff": 3.0})


@pytest.mark.parametrize(
    ("numerator", "denominator"),
    [([0.0, 0.0, 4.0], [1.0, 3.2, 4.0]), ([1.0, 0.0, 0.0], [1.0, 2.0, 1.0]), ([0.0, 1.0, 0.0], [1.0, 0.7, 6.25])],
)
def test_tustin_sections_equal_python_control(numerator: list[float], denominator: list[float]) -> None:
    expected = control.sample_system(control.tf(numerator, denominator), DT, method="tustin")
    row = tustin_second_order(np.array(numerator), np.array(denominator), DT)
    assert row[:3] == pytest.approx(np.asarray(expected.num[0][0]), abs=1e-12)
    assert row[3:] == pytest.approx(np.asarray(expected.den[0][0]), abs=1e-12)


def test_tustin_first_order_equals_python_control() -> None:
    expected = control.sample_system(control.tf([1.0, 0.0], [1.0, 0.3]), DT, method="tustin")
    row = tustin_first_order(np.array([1.0, 0.0]), np.array([1.0, 0.3]), DT)
    assert row[:2] == pytest.approx(np.asarray(expected.num[0][0]), abs=1e-12)
    assert row[3:5] == pytest.approx(np.asarray(expected.den[0][0]), abs=1e-12)
    assert row[2] == 0.0 and row[5] == 0.0
