"""The worker process: spawned for real, driven through `WorkerClient`, and orphaned by a killed service."""

from __future__ import annotations

import multiprocessing
import os
import signal
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from benchmarks.fault_harness import wait_for
from core.plan.rejection import PrescriptionRejected
from server.realtime.client import WorkerClient
from server.realtime.loop import FixedRateLoop, LoopConfigError
from server.realtime.shm import Seqlock, SharedRing
from server.realtime.telemetry import EVENT_DTYPE, TELEMETRY_DTYPE, decode_events, state_dict
from server.robotd.playback import plan_and_load

LONG_SINE = {
    "segments": [
        {"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 1.0, "frequency_hz": 0.5}, "duration_s": 120.0}
    ]
}
TOO_FAST = {
    "segments": [
        {
            "cue": {"kind": "square_wave", "axis": "x", "amplitude_m_s2": 2.0, "period_s": 2.0},
            "duration_s": 4.0,
            "limits": {"slider_velocity_max_m_s": 0.05},
        }
    ]
}


TOLERANT_DRIVES = {"communication_timeout_s": 1.0}


@pytest.mark.parametrize("rate", [100, 249, 2001, 1000.0, True])
def test_control_rates_outside_250_to_2000_hz_are_refused_naming_the_field(rate: object) -> None:
    with pytest.raises(LoopConfigError) as refused:
        FixedRateLoop(rate)  # type: ignore[arg-type]
    assert refused.value.field == "control_rate_hz"
    with pytest.raises(LoopConfigError):
        WorkerClient(None, "kinematic", rate)  # type: ignore[arg-type]


@pytest.mark.slow
def test_a_started_worker_has_already_published_its_state() -> None:
    """`start` returns only once the loop has written a first state: a refusal read at once must not see the
    blank record (hal "unconfigured"; seen in a CI run on the loaded machine)."""
    with WorkerClient(None, "kinematic", hal_options=TOLERANT_DRIVES) as client:
        state = client.latest_state()
        assert (state["state"], state["hal_state"]) == ("idle", "configured")


@pytest.mark.slow
def test_client_session_refusal_motion_emergency_stop_and_reset() -> None:
    # A generous drive communication timeout: on a shared test machine the worker can stall for tens of ms,
    # and the drives' own stop has its own test (test_supervisor).
    with WorkerClient(None, "kinematic", hal_options=TOLERANT_DRIVES) as client:
        with pytest.raises(PrescriptionRejected) as refused:
            plan_and_load(client, TOO_FAST)
        assert refused.value.limit == "slider_velocity"
        state = client.latest_state()
        assert state["state"] == "idle" and state["hal_state"] == "configured"  # refused before any motion
        assert not np.any(client.drain_telemetry()["hal_state"] == 2)  # the HAL was never active

        playback, report = plan_and_load(client, LONG_SINE, {"body_mass_kg": 70.0, "height_m": 1.75})
        assert report["peak_use"]["tilt"] < 1.0
        playback.start(client)
        try:
            wait_for(lambda: abs(client.latest_state()["stance_pose"][1]) > 1e-3, 30.0, "motion")
        except AssertionError as error:
            raise AssertionError(f"{error}: {client.latest_state()['state']}, {client.drain_events()}") from None
        running = client.latest_state()
        assert running["state"] == "running" and running["plate_force_z_n"][0] > 100.0  # the patient stands on it
        client.emergency_stop()
        wait_for(lambda: client.latest_state()["hal_state"] == "estop", 30.0, "drives disabled")
        stopped = client.latest_state()
        assert stopped["state"] == "estop" and stopped["estop_latched"] and stopped["stop_reason"] == "emergency_stop"
        events = client.drain_events()
        latency = [e for e in events if e["kind"] == "estop_reached_hal"]
        assert latency and latency[0]["details"]["latency_ms"] < 1000.0
        assert {"worker_started", "prescription_checked", "emergency_stop", "standstill"} <= {e["kind"] for e in events}
        assert all("utc" in e and "tick_time_s" in e for e in events)
        telemetry = client.drain_telemetry()
        assert len(telemetry) > 100 and np.all(np.diff(telemetry["tick"]) > 0)
        client.reset()
        wait_for(lambda: client.latest_state()["state"] == "idle", 30.0, "the reset")
        # A further 200 ms of the worker's own ticks: a motion the reset restarted would show by then.
        reset_tick = int(client.latest_state()["tick"])
        wait_for(lambda: client.latest_state()["tick"] >= reset_tick + 200, 30.0, "200 ticks after the reset")
        after = client.latest_state()
        assert after["state"] == "idle" and after["hal_state"] == "configured"
        np.testing.assert_array_equal(after["slider_command_m"], stopped["slider_command_m"])  # no motion restarted


def _service(prescription: dict[str, Any], report: Any, hold: Any) -> None:
    """A stand-in for the console service: start a worker, get it moving, tell the test, then wait."""
    client = WorkerClient(None, "kinematic", hal_options=TOLERANT_DRIVES)
    client.start()
    playback, _ = plan_and_load(client, prescription)
    playback.start(client)
    report.send({"state": client.state.name, "events": client.events.name, "worker_pid": client.worker_pid})
    hold.recv()  # blocks until the test kills us


def _process_gone(pid: int) -> bool:
    status = Path(f"/proc/{pid}/status")
    try:
        return "State:\tZ" in status.read_text()
    except FileNotFoundError:
        return True


@pytest.mark.slow
def test_killing_the_service_mid_session_makes_the_worker_stop_safely() -> None:
    context = multiprocessing.get_context("spawn")
    report_reader, report_writer = context.Pipe(duplex=False)
    hold_reader, hold_writer = context.Pipe(duplex=False)
    service = context.Process(target=_service, args=(LONG_SINE, report_writer, hold_reader))
    service.start()
    try:
        assert report_reader.poll(120), "the service did not start its worker"
        names = report_reader.recv()
        state = Seqlock(TELEMETRY_DTYPE, names["state"])
        events = SharedRing(EVENT_DTYPE, 1 << 10, names["events"])
        try:
            wait_for(lambda: abs(state_dict(state.read()[0])["stance_pose"][1]) > 2e-3, 60.0, "the platform to move")
        except AssertionError as error:
            seen = [(e["kind"], e["details"]) for e in decode_events(events.drain())]
            raise AssertionError(f"{error}: {state_dict(state.read()[0])['state']}, events {seen}") from None
        assert state_dict(state.read()[0])["state"] == "running"
        os.kill(service.pid, signal.SIGKILL)  # the service dies mid-session
        service.join(10)
        wait_for(lambda: state_dict(state.read()[0])["state"] == "stopped", 30.0, "a safe stop")
        final = state_dict(state.read()[0])
        assert final["stop_reason"] in ("service_lost", "watchdog")
        assert final["hal_state"] == "configured"  # drives off
        np.testing.assert_allclose(final["stance_pose"], 0.0, atol=1e-9)  # returned to neutral first
        kinds = [event["kind"] for event in decode_events(events.drain())]
        assert "controlled_stop" in kinds and "drives_disabled" in kinds
        wait_for(lambda: _process_gone(names["worker_pid"]), 20.0, "the orphaned worker to exit")
    finally:
        if service.is_alive():
            service.kill()
        hold_writer.close()
