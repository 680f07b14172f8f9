"""Shared by the CANopen tests: a configuration with brisk homing, and a check that no thread outlives a test."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from server.hal.canopen.units import DriveConfiguration, load_drive_configuration


def brisk_configuration(heartbeat_timeout_ms: int = 500) -> DriveConfiguration:
    """The shipped configuration with brisk homing, so tests spend little wall time homing, and a
    heartbeat timeout that survives a test machine stalling the whole process for a few hundred ms."""
    shipped = load_drive_configuration()
    fast = dataclasses.replace(
        shipped.axes[0].drive_type,
        homing_switch_speed_mm_s=250.0,
        homing_zero_speed_mm_s=20.0,
        homing_acceleration_mm_s2=5000.0,
    )
    axes = tuple(dataclasses.replace(axis, drive_type=fast) for axis in shipped.axes)
    return dataclasses.replace(shipped, axes=axes, heartbeat_timeout_ms=heartbeat_timeout_ms)


def wait_until(predicate: Callable[[], bool], timeout_s: float) -> bool:
    """Poll `predicate` until true or `timeout_s` passes (an event-based wait, generous by design)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


@pytest.fixture(autouse=True)
def no_leaked_threads() -> Iterator[None]:
    """Fails a test that leaves a bus, node or drive thread running (import it into the test module)."""
    before = set(threading.enumerate())
    yield
    deadline = time.monotonic() + 2.0
    while time.monotonic() < deadline:
        leaked = [t for t in set(threading.enumerate()) - before if t.is_alive()]
        if not leaked:
            return
        time.sleep(0.02)
    pytest.fail(f"threads left running: {leaked}")
