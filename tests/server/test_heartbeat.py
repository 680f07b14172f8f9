"""The heartbeat relay: a busy service keeps the session; a dead or hung one stops it."""

from __future__ import annotations

import ctypes
import multiprocessing
import threading
import time
from typing import Any

import numpy as np
import pytest

from server.realtime.client import WorkerClient
from server.realtime.heartbeat import SERVICE_STALL_TOLERANCE_S, relay_heartbeats
from server.realtime.shm import ControlBlock

PERIOD_S = 0.01


def _relay_in_thread(control: ControlBlock) -> tuple[threading.Thread, Any]:
    link, service_end = multiprocessing.Pipe(duplex=False)
    thread = threading.Thread(target=relay_heartbeats, args=(control, link, PERIOD_S, 0.2), daemon=True)
    thread.start()
    return thread, service_end


def _relay_beats_over(control: ControlBlock, seconds: float, *, service_beating: bool) -> int:
    start = int(control.fields["relay_beats"][0])
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if service_beating:
            control.fields["service_beats"] += np.uint64(1)
        time.sleep(PERIOD_S)
    return int(control.fields["relay_beats"][0]) - start


def test_relay_beats_while_the_service_shows_life_and_stops_when_it_stalls() -> None:
    control = ControlBlock()
    try:
        thread, service_end = _relay_in_thread(control)
        assert _relay_beats_over(control, 0.3, service_beating=True) >= 10
        time.sleep(0.25)  # past the 0.2 s stall tolerance
        assert _relay_beats_over(control, 0.3, service_beating=False) == 0
        assert _relay_beats_over(control, 0.3, service_beating=True) >= 10  # life again: beats again
        service_end.close()
        thread.join(2.0)
        assert not thread.is_alive()  # the service's goodbye (or death): the relay ends
    finally:
        control.close()


def test_relay_ends_at_once_when_the_service_dies() -> None:
    control = ControlBlock()
    try:
        thread, service_end = _relay_in_thread(control)
        del service_end  # the only handle on the service's end: like the service process dying
        thread.join(1.0)
        assert not thread.is_alive()
    finally:
        control.close()


SINE = {
    "segments": [{"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.5}, "duration_s": 60.0}]
}


def _hold_the_gil(seconds: float) -> None:
    """Block every thread of this process: ctypes.PyDLL calls keep the GIL, unlike ordinary ctypes calls."""
    ctypes.PyDLL(None).usleep(int(seconds * 1e6))


def _wait_for(predicate: Any, timeout_s: float, what: str) -> None:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return
        time.sleep(0.02)
    raise AssertionError(f"timed out waiting for {what}")


@pytest.mark.slow
def test_a_busy_service_keeps_the_session_and_a_hung_one_stops_it() -> None:
    with WorkerClient(None, "kinematic", hal_options={"communication_timeout_s": 2.0}) as client:
        client.load_prescription(SINE, {"body_mass_kg": 70.0, "height_m": 1.75})
        client.start_motion()
        _wait_for(lambda: client.latest_state()["state"] == "running", 30.0, "running")
        # Three times the 100 ms watchdog with every service thread blocked: the relay keeps beating.
        _hold_the_gil(0.3)
        time.sleep(0.2)
        busy = client.latest_state()
        assert busy["state"] == "running", (busy["state"], busy["stop_reason"], client.drain_events())
        # Past the relay's stall tolerance the service counts as hung: the watchdog stops the motion.
        _hold_the_gil(SERVICE_STALL_TOLERANCE_S + 0.4)
        _wait_for(lambda: client.latest_state()["state"] in ("stopping", "stopped"), 5.0, "a controlled stop")
        assert client.latest_state()["stop_reason"] == "watchdog"
