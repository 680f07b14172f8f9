"""Twelve simulated CiA 402 drives and the `canopen` HAL on python-can's virtual bus, at a 1 ms period.

Measures each control cycle's round trip (RPDOs + SYNC out, all 24 TPDOs back), the CPU it costs, and
how much of a paced 1 kHz loop makes its deadline. Baseline in the same run: one frame's round trip
through the same virtual bus and receive threads. The drives run in this process, so process CPU
counts master and simulated drives together. For a real bus the per-cycle frame bits say which
period one 1 Mbit/s CAN bus can carry.
"""

from __future__ import annotations

import os
import threading
import time
import uuid
from typing import Any

import can
import numpy as np

from core.robot import default_twin
from server.hal.base import HalCommand, HalReading
from server.hal.canopen.master import MAX_BUS_LOAD, CanopenHal, create_canopen_hal
from server.hal.canopen.pdo import cycle_bus_bits
from server.hal.canopen.units import load_drive_configuration

CONTROL_PERIOD_S = 0.001
TARGET_ROUND_TRIP_MS = 1.0  # the whole cycle must come back within one period
TARGET_CPU_MS = 1.0
CAN_BITRATE = 1_000_000


def _percentiles_ms(samples_ns: list[int]) -> dict[str, float]:
    values = np.asarray(samples_ns) / 1e6
    return {
        "median": round(float(np.median(values)), 4),
        "p99": round(float(np.percentile(values, 99)), 4),
        "max": round(float(values.max()), 4),
    }


def single_frame_round_trip(count: int) -> list[int]:
    """Baseline: one frame out, one frame back through python-can's virtual bus and Notifier threads."""
    channel = f"bench-ping-{uuid.uuid4().hex[:8]}"
    master = can.Bus(interface="virtual", channel=channel)
    responder = can.Bus(interface="virtual", channel=channel)
    answered = threading.Event()
    reply = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False)

    def answer(msg: can.Message) -> None:
        responder.send(reply)

    def received(msg: can.Message) -> None:
        answered.set()

    responder_notifier = can.Notifier(responder, [answer], timeout=0.05)
    master_notifier = can.Notifier(master, [received], timeout=0.05)
    request = can.Message(arbitration_id=0x80, data=b"", is_extended_id=False)
    samples = []
    try:
        for _ in range(count):
            answered.clear()
            began = time.perf_counter_ns()
            master.send(request)
            answered.wait(0.1)
            samples.append(time.perf_counter_ns() - began)
    finally:
        master_notifier.stop()
        responder_notifier.stop()
        master.shutdown()
        responder.shutdown()
    return samples


def _enabled_hal() -> CanopenHal:
    configuration = load_drive_configuration().with_homing_method(37)  # reference in place: no homing run
    hal = create_canopen_hal(
        default_twin(),
        CONTROL_PERIOD_S,
        "virtual",
        f"bench-{uuid.uuid4().hex[:8]}",
        configuration=configuration,
        simulate=12,
    )
    hal.configure()
    hal.home()
    hal.activate()
    return hal


def _profile(hal: CanopenHal, start: np.ndarray, k: int) -> np.ndarray:
    return start + hal.scaling.direction * 0.01 * (1.0 - np.cos(2.0 * np.pi * k / 1000.0)) / 2.0


def run(*, quick: bool) -> dict[str, Any]:
    load_average = os.getloadavg()[0]  # the drives share this process and the CPUs with everything else
    cycles = 300 if quick else 3000
    paced_cycles = 300 if quick else 2000
    baseline = single_frame_round_trip(cycles)
    hal = _enabled_hal()
    try:
        reading, command = HalReading(), HalCommand()
        hal.read(reading)
        start = reading.positions_m.copy()
        round_trips, master_cpu, late = [], [], 0
        process_cpu_began, wall_began = time.process_time(), time.perf_counter()
        for k in range(cycles):
            command.positions_m[:] = _profile(hal, start, k)
            cpu_began = time.thread_time_ns()
            began = time.perf_counter_ns()
            hal.write(command)
            cpu_write = time.thread_time_ns() - cpu_began
            late += not hal.wait_for_feedback(1.0)  # lock-step: each round trip is its own cycle's
            round_trips.append(time.perf_counter_ns() - began)
            cpu_began = time.thread_time_ns()
            hal.read(reading)
            master_cpu.append(cpu_write + time.thread_time_ns() - cpu_began)
        wall_s = time.perf_counter() - wall_began
        process_cpu_ms = (time.process_time() - process_cpu_began) / cycles * 1e3

        # Paced at 1 kHz: a cycle makes its deadline when all its TPDOs are back before the next SYNC.
        met, next_tick = 0, time.perf_counter()
        paced_began = time.perf_counter()
        for k in range(cycles, cycles + paced_cycles):
            command.positions_m[:] = _profile(hal, start, k)
            hal.write(command)
            if hal.wait_for_feedback(max(0.0, next_tick + CONTROL_PERIOD_S - time.perf_counter())):
                met += 1
            hal.read(reading)
            next_tick += CONTROL_PERIOD_S
            time.sleep(max(0.0, next_tick - time.perf_counter()))
        paced_s = time.perf_counter() - paced_began
        hal.deactivate()
        faults = [e["message"] for e in hal.drain_events() if e["kind"] not in ("homed",)]
    finally:
        hal.shutdown()

    od_bits = cycle_bus_bits(12, _object_dictionary())
    round_trip = _percentiles_ms(round_trips)
    return {
        "drives": 12,
        "control_period_ms": CONTROL_PERIOD_S * 1e3,
        "cycles": cycles,
        "round_trip_ms": round_trip,
        "round_trip_target_ms": TARGET_ROUND_TRIP_MS,
        "round_trip_target_met": round_trip["p99"] <= TARGET_ROUND_TRIP_MS,
        "cycles_without_full_answer_within_1s": late,
        "master_cpu_per_cycle_ms": _percentiles_ms(master_cpu),
        "process_cpu_per_cycle_ms": round(process_cpu_ms, 4),
        "cpu_target_ms": TARGET_CPU_MS,
        "cpu_target_met": process_cpu_ms <= TARGET_CPU_MS,
        "unpaced_rate_hz": round(cycles / wall_s, 1),
        "paced_1khz": {
            "cycles": paced_cycles,
            "deadlines_met_fraction": round(met / paced_cycles, 4),
            "achieved_rate_hz": round(paced_cycles / paced_s, 1),
        },
        "baseline_single_frame_round_trip_ms": _percentiles_ms(baseline),
        "round_trip_over_single_frame": round(round_trip["median"] / _percentiles_ms(baseline)["median"], 1),
        "frames_per_cycle": 1 + 12 * 3,
        "real_can_bits_per_cycle": od_bits,
        "real_can_min_period_ms_at_1mbit": {
            "full_load": round(od_bits / CAN_BITRATE * 1e3, 3),
            f"at_{MAX_BUS_LOAD:.0%}_load": round(od_bits / (MAX_BUS_LOAD * CAN_BITRATE) * 1e3, 3),
        },
        "faults_during_run": faults,
        "load_average_1min_at_start": round(load_average, 2),
    }


def _object_dictionary() -> Any:
    import canopen

    return canopen.import_od(str(load_drive_configuration().axes[0].drive_type.eds_path))
