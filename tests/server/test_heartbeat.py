"""The heartbeat relay: a busy service keeps the session; a dead or hung one stops it."""

from __future__ import annotations

import ctypes
import multiprocessing
import threading
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from benchmarks.fault_harness import wait_for
from server.realtime import heartbeat
from server.realtime.client import WorkerClient
from server.realtime.heartbeat import SERVICE_STALL_TOLERANCE_S, relay_heartbeats
from server.realtime.shm import ControlBlock
from server.robotd.playback import plan_and_load

PERIOD_S = 0.01
STALL_TOLERANCE_S = 0.2
THREAD_TIMEOUT_S = 30.0  # generous: a loaded 2-core machine may not schedule the relay's thread for a while


def _relay_in_thread(control: ControlBlock) -> tuple[threading.Thread, Any]:
    link, service_end = multiprocessing.Pipe(duplex=False)
    thread = threading.Thread(target=relay_heartbeats, args=(control, link, PERIOD_S, STALL_TOLERANCE_S), daemon=True)
    thread.start()
    return thread, service_end


def _beat_until(control: ControlBlock, done: threading.Event) -> None:
    """The service showing life: a beat every period until `done`."""
    while not done.wait(PERIOD_S):
        control.fields["service_beats"] += np.uint64(1)


def test_relay_beats_while_the_service_shows_life_and_ends_with_its_goodbye() -> None:
    control = ControlBlock()
    done = threading.Event()
    try:
        thread, service_end = _relay_in_thread(control)
        beater = threading.Thread(target=_beat_until, args=(control, done), daemon=True)
        beater.start()
        start = int(control.fields["relay_beats"][0])
        wait_for(lambda: int(control.fields["relay_beats"][0]) >= start + 10, THREAD_TIMEOUT_S, "ten relay beats")
        done.set()
        beater.join(THREAD_TIMEOUT_S)
        service_end.close()
        thread.join(THREAD_TIMEOUT_S)
        assert not thread.is_alive()  # the service's goodbye (or death): the relay ends
    finally:
        done.set()
        control.close()


@dataclass
class ScriptedService:
    """The service's end of the relay's link, played one relay period at a time on a clock that only this
    script advances: each poll of the link is one period, in which the service beats or not. The relay's
    count is read at every poll, so its decisions are checked period by period with no wall-clock timing."""

    control: ControlBlock
    beating: list[bool]  # per period: did the service beat in it?
    clock_s: float = 0.0
    relay_beats: list[int] = field(default_factory=list)

    def poll(self, timeout_s: float) -> bool:
        period = len(self.relay_beats)
        self.relay_beats.append(int(self.control.fields["relay_beats"][0]))
        if period == len(self.beating):
            return True  # the script is over: the service says goodbye
        self.clock_s += timeout_s
        if self.beating[period]:
            self.control.fields["service_beats"] += np.uint64(1)
        return False

    def monotonic(self) -> float:
        return self.clock_s


def test_relay_stops_beating_once_the_service_stalls_past_the_tolerance_and_beats_again_at_its_life(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    period_s, tolerance_s = 1 / 64, 0.25  # exact in binary: the tolerance is exactly 16 periods
    live, stalled, live_again = 30, 40, 20
    control = ControlBlock()
    try:
        service = ScriptedService(control, [True] * live + [False] * stalled + [True] * live_again)
        monkeypatch.setattr(heartbeat, "time", SimpleNamespace(monotonic=service.monotonic))
        relay_heartbeats(control, service, period_s, tolerance_s)  # type: ignore[arg-type]
        beats_per_period = np.diff(service.relay_beats).tolist()
        within_tolerance = round(tolerance_s / period_s)
        assert beats_per_period == (
            [1] * live + [1] * within_tolerance + [0] * (stalled - within_tolerance) + [1] * live_again
        )
    finally:
        control.close()


def test_relay_ends_at_once_when_the_service_dies() -> None:
    control = ControlBlock()
    try:
        thread, service_end = _relay_in_thread(control)
        del service_end  # the only handle on the service's end: like the service process dying
        thread.join(THREAD_TIMEOUT_S)  # no beat ever came, so only the link's EOF can end the relay
        assert not thread.is_alive()
    finally:
        control.close()


SINE = {
    "segments": [{"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.5}, "duration_s": 60.0}]
}
WATCHDOG_TICKS = 100  # the worker's 100 ms watchdog ages by one period per tick, at 1 kHz


def _hold_the_gil(seconds: float) -> None:
    """Block every thread of this process: ctypes.PyDLL calls keep the GIL, unlike ordinary ctypes calls."""
    ctypes.PyDLL(None).usleep(int(seconds * 1e6))


@pytest.mark.slow
def test_a_busy_service_keeps_the_session_and_a_hung_one_stops_it() -> None:
    with WorkerClient(None, "kinematic", hal_options={"communication_timeout_s": 2.0}) as client:
        playback, _ = plan_and_load(client, SINE, {"body_mass_kg": 70.0, "height_m": 1.75})
        playback.start(client)
        wait_for(lambda: client.latest_state()["state"] == "running", 30.0, "running")
        # Three times the 100 ms watchdog with every service thread blocked: the relay keeps beating.
        _hold_the_gil(0.3)
        # Two more watchdog windows of the worker's own ticks: a late watchdog stop would show by then.
        after_hold = int(client.latest_state()["tick"])
        wait_for(lambda: client.latest_state()["tick"] >= after_hold + 2 * WATCHDOG_TICKS, 30.0, "two watchdog windows")
        busy = client.latest_state()
        assert busy["state"] == "running", (busy["state"], busy["stop_reason"], client.drain_events())
        # Past the relay's stall tolerance the service counts as hung: the watchdog stops the motion.
        _hold_the_gil(SERVICE_STALL_TOLERANCE_S + 0.4)
        wait_for(lambda: client.latest_state()["state"] in ("stopping", "stopped"), 30.0, "a controlled stop")
        assert client.latest_state()["stop_reason"] == "watchdog"
