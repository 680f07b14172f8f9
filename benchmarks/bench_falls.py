"""Per-tick cost of the simulated patient and of the fall monitor, and batch simulation speed.

Targets (issue 8 brief): `SimulatedPatient.step` ≤ 20 µs and `FallMonitor.step` well inside a 1 ms tick.
The baseline is a bare call into a numba function with the same three small arrays, measured in the same
run, so the ratio says how much the patient model costs beyond the call itself.
"""

from __future__ import annotations

import time
from typing import Any

import numba
import numpy as np

from benchmarks.timing import per_call_us
from core.falls import FallDetectorConfig, FallMonitor
from core.patient import PatientParameters, SimulatedPatient, simulate

PERIOD_S = 0.001
STEP_TARGET_US = 20.0
MONITOR_TARGET_US = 20.0


@numba.njit(cache=True)
def _bare_call(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> float:
    return a[0] + b[0] + c[0]


def run(*, quick: bool) -> dict[str, Any]:
    count = 20_000 if quick else 200_000
    params = PatientParameters.preset("healthy", 75.0, 1.78)
    patient = SimulatedPatient(params, PERIOD_S, seed=0)
    acceleration, tilt, angular_velocity = np.zeros(3), np.zeros(2), np.zeros(3)
    patient.step(acceleration, tilt, angular_velocity)
    _bare_call(acceleration, tilt, angular_velocity)
    baseline_us = per_call_us(lambda: _bare_call(acceleration, tilt, angular_velocity), count)
    step_us = per_call_us(lambda: patient.step(acceleration, tilt, angular_velocity), count)

    monitor = FallMonitor(FallDetectorConfig.for_patient(75.0, 1.78), PERIOD_S)
    forces, cops = np.full(2, 0.5 * params.body_weight_n), np.zeros((2, 2))
    monitor_us = per_call_us(lambda: monitor.step(0.0, forces, cops, 0.0), count)

    samples = 60_000 if quick else 600_000
    zeros3, zeros2 = np.zeros((samples, 3)), np.zeros((samples, 2))
    simulate(params, PERIOD_S, 0, zeros3[:10], zeros2[:10], zeros3[:10])
    start = time.perf_counter()
    simulate(params, PERIOD_S, 0, zeros3, zeros2, zeros3)
    batch_s = time.perf_counter() - start
    return {
        "patient_step_us": round(step_us, 2),
        "patient_step_target_us": STEP_TARGET_US,
        "patient_step_met": step_us <= STEP_TARGET_US,
        "baseline_numba_call_us": round(baseline_us, 2),
        "patient_step_over_baseline": round(step_us / baseline_us, 1),
        "fall_monitor_step_us": round(monitor_us, 2),
        "fall_monitor_target_us": MONITOR_TARGET_US,
        "fall_monitor_met": monitor_us <= MONITOR_TARGET_US,
        "batch_simulated_s": samples * PERIOD_S,
        "batch_wall_s": round(batch_s, 3),
        "batch_faster_than_real_time": round(samples * PERIOD_S / batch_s, 0),
    }
