"""Balance trends (issue 16 defect 6 and §5): by date, one unit per series, Prieto's measures on low-pass
filtered COP, faulted runs marked, every series in one request."""

from __future__ import annotations

import math

import numpy as np
import pytest
from fastapi.testclient import TestClient

from core.patient import PatientParameters, simulate_trial
from core.posturography import filtered_sway_metrics, lowpass_cop, sway_metrics
from core.robot import default_twin
from server.realtime.telemetry import TELEMETRY_DTYPE, SupervisorState
from server.sessions.balance import run_balance
from tests.server.conftest import FakeWorker, Seed, booked_session, run_columns, wait_until

TWIN = default_twin()
PERIOD_S = 0.001


def quiet_stance(seed: int, cop_noise_m: float = 0.001) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """30 s of simulated quiet stance at 1 kHz: time, plate forces (N, 2) and plate COPs (N, 2, 2)."""
    params = PatientParameters.preset("healthy", 70.0, 1.75, plate_cop_noise_m=cop_noise_m)
    _, trial = simulate_trial(params, [], 30.0, PERIOD_S, seed)
    return trial.time_s, trial.plate_force_z_n, trial.plate_cop_m


def test_mean_cop_velocity_of_quiet_stance_is_sway_not_sensor_noise() -> None:
    """Defect 6: path length on raw 1 kHz COP read 1.6-2.0 m/s for standing patients."""
    time_s, forces, cops = quiet_stance(3)
    metrics = run_balance(run_columns(time_s, forces, cops), TWIN)
    assert metrics is not None
    assert 0.001 < metrics["mean_velocity_m_s"] < 0.1, metrics["mean_velocity_m_s"]
    # The filter takes out the plate's noise, not the sway: the noise-free plate gives about the same figure.
    _, _, clean = quiet_stance(3, cop_noise_m=0.0)
    noise_free = run_balance(run_columns(time_s, forces, clean), TWIN)
    assert noise_free is not None
    assert metrics["mean_velocity_m_s"] == pytest.approx(noise_free["mean_velocity_m_s"], rel=0.35)
    assert metrics["rms_distance_m"] == pytest.approx(noise_free["rms_distance_m"], rel=0.1)
    raw = sway_metrics(time_s, cops[:, 0])
    assert raw.mean_velocity_m_s > 10 * metrics["mean_velocity_m_s"]  # what the unfiltered path length said


def test_a_run_stopped_after_a_few_seconds_has_no_sway_measures() -> None:
    """Issue 22 §6: sway measures were computed and trended for runs stopped after 2–4 s."""
    time_s, forces, cops = quiet_stance(4)
    short = slice(0, 4000)
    assert run_balance(run_columns(time_s[short], forces[short], cops[short]), TWIN) is None
    assert run_balance(run_columns(time_s, forces, cops), TWIN) is not None  # 30 s: measured


def test_the_window_is_the_run_in_motion_and_says_where_it_is() -> None:
    """Issue 22 §6: "Duration analysed" read 75.9 s for a 69.1 s run: the recording's tail after the end (and the
    wait before the start) counted, though the plates still carried the patient."""
    time_s, forces, cops = quiet_stance(5)
    state = np.full(len(time_s), int(SupervisorState.RUNNING), dtype=np.uint8)
    state[:2000] = int(SupervisorState.READY)  # before the start
    state[26000:] = int(SupervisorState.STOPPED)  # the tail after the end
    metrics = run_balance(run_columns(time_s, forces, cops, state), TWIN)
    assert metrics is not None
    assert metrics["window_from_s"] == pytest.approx(2.0) and metrics["window_to_s"] == pytest.approx(25.999)
    assert metrics["duration_s"] == pytest.approx(23.999)


def test_lowpass_keeps_slow_sway_and_resamples_a_late_tick() -> None:
    time_s = np.arange(5000) * PERIOD_S
    time_s[2000:] += 0.0004  # one late tick: the rest of the record is shifted
    cop = np.column_stack([0.01 * np.sin(2 * math.pi * 0.4 * time_s), np.zeros_like(time_s)])
    uniform, filtered = lowpass_cop(time_s, cop)
    assert np.allclose(np.diff(uniform), PERIOD_S)
    assert np.max(np.abs(filtered[100:-100, 0] - 0.01 * np.sin(2 * math.pi * 0.4 * uniform[100:-100]))) < 2e-4
    metrics = filtered_sway_metrics(time_s, cop)
    assert metrics.range_ap_m == pytest.approx(0.02, rel=0.02)
    assert metrics.mean_distance_m == pytest.approx(0.01 * 2 / math.pi, rel=0.05)  # mean |sin| of a sine


def _record(fake_worker: FakeWorker, forces: np.ndarray, cops: np.ndarray) -> None:
    """Telemetry with the given plate readings, as the worker's ring would hold it."""
    samples = len(forces)
    records = np.zeros(samples, dtype=TELEMETRY_DTYPE)
    with fake_worker._lock:
        ticks = np.arange(fake_worker.tick, fake_worker.tick + samples)
        records["tick"] = ticks
        records["time_s"] = ticks / fake_worker.sample_rate_hz
        records["session_time_s"] = (ticks - ticks[0]) / fake_worker.sample_rate_hz
        records["state"] = int(SupervisorState.RUNNING)
        records["plate_force_z_n"] = forces
        records["plate_cop_m"] = cops
        fake_worker.tick += samples
        fake_worker._telemetry.append(records)


def _run(
    client: TestClient, seed: Seed, fake_worker: FakeWorker, patient: dict, stop_reason: str, cop_seed: int
) -> tuple[int, dict]:
    booked = booked_session(client, seed.headers(), **patient)
    response = client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers())
    assert response.status_code == 200, response.text
    run = response.json()
    _, forces, cops = quiet_stance(cop_seed)
    _record(fake_worker, forces[:22000], cops[:22000])  # 22 s: longer than the shortest window measured
    url = f"/api/v1/runs/{run['id']}"
    wait_until(lambda: client.get(url, headers=seed.headers()).json()["sample_count"] == 22000)
    if stop_reason == "fall":
        fake_worker.emit_event("fall", onset_s=3.0, detected_s=3.2, session_time_s=3.2)
    fake_worker.emit_event("controlled_stop", reason=stop_reason)
    wait_until(lambda: client.get(url, headers=seed.headers()).json().get("outcome") is not None)
    return booked.patient_id, run


def test_trends_come_in_one_request_by_date_with_one_unit_per_series(
    robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    patient = {"identifier": "MRN-TREND", "name": "Trend Patient"}
    patient_id, first = _run(robot_client, seed, fake_worker, patient, "completed", 1)
    response = robot_client.get(f"/api/v1/patients/{patient_id}/trends", headers=seed.headers())
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["method"]["filter"]["cutoff_hz"] == 5.0 and "Prieto" in body["method"]["definitions"]
    runs = body["runs"]
    assert [run["run_id"] for run in runs][:1] == [first["id"]]
    assert runs[0]["status"] == "ok" and runs[0]["date"] == runs[0]["started_at"][:10]
    series = {entry["key"]: entry for entry in body["series"]}
    assert set(series) >= {"mean_velocity", "path_length", "rms_distance", "ellipse_area_95", "falls"}
    assert series["mean_velocity"]["unit"] == "mm/s" and series["ellipse_area_95"]["unit"] == "cm²"
    assert series["falls"]["unit"] == "falls per run"
    velocity = series["mean_velocity"]["points"][0]
    assert velocity["date"] == runs[0]["date"] and 1.0 < velocity["value"] < 100.0  # mm/s, not 1600-2000
    assert all(entry["normative"] is None for entry in body["series"])  # no band without a published source
    assert (
        robot_client.get(
            f"/api/v1/patients/{patient_id}/trends",
            params={"from_date": "2030-01-02", "to_date": "2030-01-01"},
            headers=seed.headers(),
        ).status_code
        == 422
    )
    assert robot_client.get("/api/v1/patients/999999/trends", headers=seed.headers()).status_code == 404


def test_trends_mark_falls_and_faulted_runs() -> None:
    from server.sessions.balance import run_status

    assert [run_status(o) for o in ("completed", "stopped", "fall", "limit_hit", "fault", "emergency_stop", None)] == [
        "ok",
        "ok",
        "fall",
        "faulted",
        "faulted",
        "faulted",
        "in_progress",
    ]
