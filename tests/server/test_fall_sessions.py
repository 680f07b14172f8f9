"""Whole sessions through the worker's tick pipeline with the simulated patient (issue 16 defects 3 and 4).

A 0.5 m/s² x-axis sine is ordinary training: it must end `completed`, not as a fall, for light and heavy
patients on every simulated backend. The session runs at a reduced duration (the defect showed ~3 s in).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from core.robot import default_twin
from server.hal.backends import make_hal
from server.realtime.pipeline import TickPipeline
from server.realtime.prescription import plan_prescription
from server.realtime.supervisor import SupervisorConfig
from server.realtime.telemetry import StopReason, SupervisorState

RATE_HZ = 1000
SINE_X = {"kind": "sine", "axis": "x", "amplitude_m_s2": 0.5, "frequency_hz": 0.5}


def run_session(
    backend: str, patient: dict[str, Any], cue: dict[str, Any], duration_s: float, skip_every: int = 0
) -> tuple[TickPipeline, list[tuple[int, str, str | None, dict[str, Any]]], np.ndarray]:
    """Tick a pipeline until the drives are off; `skip_every` > 0 drops every n-th period (a late worker)."""
    twin = default_twin()
    config = SupervisorConfig()
    options = {"communication_timeout_s": 60.0} if backend == "kinematic" else {}
    hal = make_hal(backend, twin, 1.0 / RATE_HZ, **options)
    hal.configure()
    hal.home()
    events: list[tuple[int, str, str | None, dict[str, Any]]] = []
    pipeline = TickPipeline(
        twin,
        hal,
        RATE_HZ,
        config,
        lambda kind, details, detector: events.append((pipeline.tick_index, kind, detector, details)),
    )
    plan = plan_prescription(
        {"segments": [{"cue": cue, "duration_s": duration_s}]},
        twin,
        control_rate_hz=RATE_HZ,
        config=config,
        patient=patient,
    )
    pipeline.load(plan)
    pipeline.heartbeat()
    pipeline.start()
    session_times = []
    for tick in range(round((duration_s + 30.0) * RATE_HZ)):
        pipeline.heartbeat()
        lateness_ns = 0
        if skip_every and tick % skip_every == skip_every - 1:
            lateness_ns = round(1e9 / RATE_HZ)  # one period late: the loop skipped a deadline
        pipeline.tick(lateness_ns)
        if "session_time_s" in pipeline.record.dtype.names:
            session_times.append(float(pipeline.record["session_time_s"][0]))
        if not pipeline.supervisor.drives_enabled and pipeline.supervisor.state is not SupervisorState.RUNNING:
            break
    hal.shutdown()
    return pipeline, events, np.asarray(session_times)


SIM_HEAVY_PATIENT_UNSTABLE = pytest.mark.xfail(
    strict=True,
    reason="server/sim: the horizontal force that carries the patient along is computed from the platform's "
    "finite-differenced acceleration of the previous step, a one-step algebraic loop that diverges with a "
    "120 kg patient (support acceleration ~ -10 m/s² with the platform at rest); reported to the HAL engineer",
)


@pytest.mark.parametrize(
    ("backend", "body_mass_kg"),
    [
        ("kinematic", 64.0),
        ("kinematic", 120.0),
        ("sim", 64.0),
        pytest.param("sim", 120.0, marks=SIM_HEAVY_PATIENT_UNSTABLE),
    ],
)
def test_a_half_m_s2_x_sine_session_completes_without_a_fall(backend: str, body_mass_kg: float) -> None:
    pipeline, events, _ = run_session(backend, {"body_mass_kg": body_mass_kg, "height_m": 1.75}, SINE_X, 12.0)
    falls = [details for _, kind, _, details in events if kind == "fall"]
    assert not falls, f"{backend}, {body_mass_kg} kg: the session ended as a fall: {falls[0]}"
    assert pipeline.supervisor.stop_reason is StopReason.COMPLETED, pipeline.supervisor.stop_reason
