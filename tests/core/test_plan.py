"""`core.plan`: the prescription model agrees with the cue generators, the robot-dependent step refuses in the
model's error shape, and the plan package stays inside `core`."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from core.cues import CUE_KINDS, cue_from_spec
from core.plan.build import plan_prescription
from core.plan.prescription import PrescriptionError, parse_prescription
from core.robot import default_twin

REPO = Path(__file__).resolve().parents[2]
MINIMAL_SEGMENT_CUE = {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.5}
CSV = "time_s,specific_force_x_m_s2,specific_force_y_m_s2,specific_force_z_m_s2\n0,0,0.5,0\n2,0,-0.5,0\n"
MINIMAL = {
    "square_wave": {"axis": "x", "amplitude_m_s2": 1.0, "period_s": 2.0},
    "step": {"axis": "roll", "final_rad_s": 0.05},
    "sine": {"axis": "pitch", "amplitude_rad_s": 0.05, "frequency_hz": 0.3},
    "multisine": {"components": [{"axis": "y", "amplitude_m_s2": 0.3, "frequency_hz": 0.2}]},
    "gait": {"cadence_steps_per_min": 90.0, "lateral_amplitude_m_s2": 0.3},
    "perturbations": {"translation_m_s2": 1.0},
    "csv_replay": {"csv": CSV},
}


def test_core_imports_nothing_from_server() -> None:
    probe = (
        "import pkgutil, importlib, sys, core\n"
        "for module in pkgutil.walk_packages(core.__path__, 'core.'):\n"
        "    importlib.import_module(module.name)\n"
        "print(sorted(m for m in sys.modules if m == 'server' or m.startswith('server.')))\n"
    )
    result = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, check=True)
    assert result.stdout.strip() == "[]", result.stdout


@pytest.mark.parametrize("kind", CUE_KINDS)
def test_the_models_defaults_are_the_generators(kind: str) -> None:
    """A cue is stored as given; generating it with the model's documented defaults filled in is the same cue."""
    cue = (
        parse_prescription({"segments": [{"cue": {"kind": kind, **MINIMAL[kind]}, "duration_s": 5.0}]}).segments[0].cue
    )
    given = cue_from_spec(cue.spec(), 0.01, seed=4).generate(20.0)
    documented = cue_from_spec(cue.model_dump(exclude_none=True), 0.01, seed=4).generate(20.0)
    for a, b in zip(given, documented, strict=True):
        np.testing.assert_array_equal(a, b)


def test_a_limit_may_only_tighten_the_robots_named_with_value_and_limit() -> None:
    twin = default_twin()
    segment = {"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.5}, "duration_s": 5.0}
    with pytest.raises(PrescriptionError) as refused:
        plan_prescription({"segments": [segment, {**segment, "limits": {"tilt_max_rad": 1.0}}]}, twin)
    error = refused.value
    assert (error.field, error.value) == ("segments[1].limits.tilt_max_rad", 1.0)
    assert f"{twin.robot.limits.tilt_max_rad:g}" in error.limit and "tighten" in error.limit
    with pytest.raises(PrescriptionError) as negative:
        plan_prescription({"segments": [{**segment, "limits": {"tilt_max_rad": -0.1}}]}, twin)
    assert negative.value.field == "segments[0].limits.tilt_max_rad" and "greater than 0" in negative.value.limit
    tight = plan_prescription({"segments": [{**segment, "limits": {"tilt_max_rad": math.radians(10.0)}}]}, twin)
    assert tight.segments[0].limits.motion.tilt_max_rad == math.radians(10.0)


def test_a_washout_that_would_ring_without_bound_is_refused_not_a_crash() -> None:
    """Found by the API's schemathesis run: a tilt damping of 5e-324 divided by zero (a 500) in the model. A
    subnormal damping is now refused at its field (issue 20: the damping range); the smallest damping in
    range still meets the rule between fields."""
    segment = {"cue": MINIMAL_SEGMENT_CUE, "duration_s": 5.0, "washout": {"tilt_damping": 5e-324}}
    with pytest.raises(PrescriptionError) as refused:
        parse_prescription({"segments": [segment]})
    assert refused.value.field == "segments[0].washout.tilt_damping" and "0.05" in refused.value.limit
    segment["washout"] = {"tilt_damping": 0.05}
    with pytest.raises(PrescriptionError) as refused:
        parse_prescription({"segments": [segment]})
    assert refused.value.field == "segments[0].washout.specific_force_limit_m_s2" and "0.99 g" in refused.value.limit
