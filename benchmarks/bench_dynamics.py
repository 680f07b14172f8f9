"""Inverse dynamics per tick and in batch, and the MuJoCo twin at 1 kHz (issue 4 targets).

- ID per tick for the twin (`TwinInverseDynamics.step`): target ≤ 50 µs;
- ID batch throughput (samples per second, both robots per sample);
- the sim at 1 kHz with drives and a simulated patient: real-time factor, target ≥ 5×.
Ratios against baselines measured in the same run: a bare numba call, and MuJoCo's bare mj_step.
"""

from __future__ import annotations

import time
from typing import Any

import mujoco
import numba
import numpy as np

from core.dynamics import PayloadModel, TwinInverseDynamics
from core.patient import PatientParameters
from core.robot import default_twin
from server.hal.sim.simulator import SimulatorOptions, TwinSimulator

TICK_TARGET_US = 50.0
REAL_TIME_TARGET = 5.0


@numba.njit(cache=True)
def _empty_kernel(values: np.ndarray) -> None:
    values[0] = values[0]


def _per_call_us(call: Any, count: int) -> tuple[float, float]:
    """Median and 99th-percentile wall time per call (µs), timed in blocks of 100 calls."""
    blocks = []
    for _ in range(count // 100):
        start = time.perf_counter_ns()
        for _ in range(100):
            call()
        blocks.append((time.perf_counter_ns() - start) / 100 / 1e3)
    return float(np.median(blocks)), float(np.percentile(blocks, 99))


def _tick(quick: bool) -> dict[str, Any]:
    dynamics = TwinInverseDynamics(default_twin(), PayloadModel.from_body(75.0, 1.75))
    pose = np.array([0.02, -0.03, 0.05, 0.05, -0.04, 0.08])
    rate = np.array([0.1, 0.2, -0.1, 0.3, 0.1, -0.2])
    acceleration = np.array([1.0, -2.0, 3.0, 0.5, -0.4, 0.6])
    count = 2_000 if quick else 50_000
    median, p99 = _per_call_us(lambda: dynamics.step(pose, rate, acceleration), count)
    scratch = np.zeros(1)
    _empty_kernel(scratch)
    baseline, _ = _per_call_us(lambda: _empty_kernel(scratch), count)
    return {
        "median_us": round(median, 2),
        "p99_us": round(p99, 2),
        "target_us": TICK_TARGET_US,
        "met": median <= TICK_TARGET_US,
        "ratio_to_empty_numba_call": round(median / baseline, 1),
    }


def _batch(quick: bool) -> dict[str, Any]:
    dynamics = TwinInverseDynamics(default_twin(), PayloadModel.from_body(75.0, 1.75))
    count = 20_000 if quick else 500_000
    rng = np.random.default_rng(0)
    poses = rng.uniform(-1, 1, (count, 6)) * [0.05, 0.05, 0.05, 0.1, 0.1, 0.1]
    rates = rng.uniform(-1, 1, (count, 6))
    accelerations = rng.uniform(-5, 5, (count, 6))
    dynamics.slider_forces(poses[:10], rates[:10], accelerations[:10])
    start = time.perf_counter()
    dynamics.slider_forces(poses, rates, accelerations)
    seconds = time.perf_counter() - start
    return {"samples": count, "seconds": round(seconds, 3), "samples_per_s": round(count / seconds)}


def _real_time_factor(quick: bool, *, patient: bool) -> dict[str, Any]:
    parameters = PatientParameters.preset("healthy", 75.0, 1.75) if patient else None
    simulator = TwinSimulator(default_twin(), SimulatorOptions(control_period_s=0.001, patient=parameters))
    simulator.drives.enable(simulator.positions_m)
    ticks = 1_000 if quick else 10_000
    start = time.perf_counter()
    for _ in range(ticks):
        simulator.advance()
    seconds = time.perf_counter() - start
    bare_start = time.perf_counter()
    for _ in range(ticks):
        mujoco.mj_step(simulator.model, simulator.data)
    bare = time.perf_counter() - bare_start
    factor = ticks * 0.001 / seconds
    return {
        "simulated_s": ticks * 0.001,
        "real_time_factor": round(factor, 2),
        "target": REAL_TIME_TARGET,
        "met": factor >= REAL_TIME_TARGET,
        "us_per_tick": round(seconds / ticks * 1e6, 1),
        "ratio_to_bare_mj_step": round(seconds / bare, 2),
    }


def run(*, quick: bool) -> dict[str, Any]:
    return {
        "id_per_tick_twin": _tick(quick),
        "id_batch_twin": _batch(quick),
        "sim_1khz_twin_with_simulated_patient": _real_time_factor(quick, patient=True),
        "sim_1khz_twin_with_rigid_payload": _real_time_factor(quick, patient=False),
    }
