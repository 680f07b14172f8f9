"""Issue 22 §5: Prieto's centre-of-pressure measures of any recording, `ssp-rehab posturography measures`.

The independent check: `tests/data/quijoux_2021_quiet_stance.csv` is 30 s of quiet stance on an AMTI force plate
at 100 Hz (samples 4000–6999 of `test.csv` in Quijoux et al. 2021's open code, github.com/Jythen/
code_descriptors_postural_control, MIT licence; COP = (My/Fz, Mx/Fz) as that code takes it, in mm). REFERENCE
holds what that code computes on the same signal, unfiltered and not resampled (its `positional` and `dynamic`
descriptors, run once by hand; the confidence circle from its mean and RMS distance with Prieto's formula, which
it does not implement). Their conventions differ slightly from Prieto's: the mean velocity over N/f instead of
the trial time (N − 1)/f, and a small-sample factor (n + 1)(n − 1)/(n(n − 2)) on the ellipse; both within the
issue's tolerance (0.5 %, areas and frequency 1 %)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core.posturography import sway_metrics
from server.cli.posturography_commands import RecordingError, measures, read_cop_csv

DATA = Path(__file__).resolve().parents[1] / "data" / "quijoux_2021_quiet_stance.csv"
REFERENCE = {
    "mean_distance_mm": 4.26117081240152,
    "rms_distance_mm": 4.944266975260087,
    "range_ml_mm": 16.9925,
    "range_ap_mm": 21.35109999999999,
    "total_excursion_mm": 392.9478294851741,
    "mean_velocity_mm_s": 13.098260982839136,
    "mean_velocity_ml_mm_s": 7.459036666666669,
    "mean_velocity_ap_mm_s": 9.132556666666666,
    "confidence_circle_area_95_mm2": 220.94404154800907,
    "confidence_ellipse_area_95_mm2": 202.96021312998897,
    "sway_area_per_second_mm2_s": 18.166320950541582,
    "mean_frequency_hz": 0.4893838311503273,
}
AREAS_AND_FREQUENCY = {"confidence_circle_area_95_mm2", "confidence_ellipse_area_95_mm2",
                       "sway_area_per_second_mm2_s", "mean_frequency_hz"}  # fmt: skip


def test_the_measures_agree_with_an_independent_implementation_on_real_force_plate_data() -> None:
    measured = measures(DATA, filtered=False)["measures"]
    assert set(measured) == set(REFERENCE)
    for key, expected in REFERENCE.items():
        tolerance = 0.01 if key in AREAS_AND_FREQUENCY else 0.005
        assert measured[key] == pytest.approx(expected, rel=tolerance), key


def test_prieto_measures_of_a_unit_square_walk_worked_by_hand() -> None:
    """Corners of a unit square, 1 s apart: every sample sqrt(0.5) from the mean; Prieto's formulas by hand."""
    metrics = sway_metrics(np.arange(4.0), np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float))
    assert metrics.mean_velocity_ap_m_s == pytest.approx(2 / 3)
    assert metrics.mean_velocity_ml_m_s == pytest.approx(1 / 3)
    assert metrics.confidence_circle_area_95_m2 == pytest.approx(math.pi * 0.5)  # no spread of the distance
    assert metrics.confidence_ellipse_area_95_m2 == pytest.approx(2 * math.pi * 19.0 * 0.25)  # F.95(2, 2) = 19
    assert metrics.sway_area_per_second_m2_s == pytest.approx(1.5 / 6)  # three triangles of 0.5, over 2·3 s
    assert metrics.mean_frequency_hz == pytest.approx(1 / (2 * math.pi * math.sqrt(0.5)))


def test_the_default_filter_lowers_path_measures_and_keeps_the_extent() -> None:
    raw = measures(DATA, filtered=False)
    filtered = measures(DATA)
    assert filtered["filter"].startswith("low-pass 5 Hz") and raw["filter"] == "none: the signal as given"
    assert filtered["measures"]["mean_velocity_mm_s"] < raw["measures"]["mean_velocity_mm_s"]
    assert filtered["measures"]["rms_distance_mm"] == pytest.approx(raw["measures"]["rms_distance_mm"], rel=0.02)


@pytest.mark.parametrize(
    ("content", "named"),
    [
        ("t,x,y\n0,0,0\n", "columns = 't,x,y'"),
        ("t_s,cop_ml_mm,cop_ap_mm\n0,0,0\n0.01,1,nan\n0.02,0,0\n", "row 3"),
        ("t_s,cop_ml_mm,cop_ap_mm\n0,0,0\n0.01,1,x\n", "row 3"),
        ("t_s,cop_ml_mm,cop_ap_mm\n0,0,0\n0.01,1,1\n", "rows = 2"),
        ("t_s,cop_ml_mm,cop_ap_mm\n0,0,0\n0.01,1,1\n0.02,0,1\n0.05,1,0\n0.06,1,1\n", "t_s at row 5 = 0.05 s"),
    ],
)
def test_a_csv_that_cannot_be_measured_is_refused_by_name(tmp_path: Path, content: str, named: str) -> None:
    path = tmp_path / "cop.csv"
    path.write_text(content)
    with pytest.raises(RecordingError, match=named.replace("(", r"\(").replace(".", r"\.")):
        read_cop_csv(path)


def test_the_command_prints_json_and_refuses_with_the_field() -> None:
    command = [sys.executable, "-m", "server.cli.main", "posturography", "measures"]
    answer = subprocess.run([*command, str(DATA), "--no-filter", "--json"], capture_output=True, text=True, check=True)
    printed = json.loads(answer.stdout)
    assert printed["measures"]["total_excursion_mm"] == pytest.approx(REFERENCE["total_excursion_mm"], rel=1e-9)
    assert printed["units"]["sway_area_per_second_mm2_s"] == "mm²/s"
    human = subprocess.run([*command, str(DATA)], capture_output=True, text=True, check=True).stdout
    assert "mean velocity, anterior-posterior" in human and "mm/s" in human and "_mm" not in human
    refused = subprocess.run([*command, "missing.csv", "--json"], capture_output=True, text=True)
    assert refused.returncode == 2 and json.loads(refused.stdout) == {"error": "file = missing.csv: no such file"}
