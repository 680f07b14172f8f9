"""Seqlock and telemetry ring: a reader in another process never sees a torn record."""

from __future__ import annotations

import multiprocessing
import time

import numba
import numpy as np
import pytest

from server.realtime import shm
from server.realtime.shm import Seqlock, SharedRing
from server.realtime.telemetry import TELEMETRY_DTYPE

FLOAT_FIELDS = [name for name in TELEMETRY_DTYPE.names or () if TELEMETRY_DTYPE[name].base == np.float64]


def _stamp(record: np.ndarray, value: int) -> None:
    """Every float of the record holds `value`, and `tick` too: a torn copy mixes two values."""
    record["tick"] = value
    for name in FLOAT_FIELDS:
        record[name] = float(value)


def _consistent(records: np.ndarray) -> bool:
    if len(records) == 0:
        return True
    ticks = records["tick"].astype(float)
    return all(np.all(records[name].reshape(len(records), -1) == ticks[:, None]) for name in FLOAT_FIELDS)


def _write_state(name: str, count: int) -> None:
    seqlock = Seqlock(TELEMETRY_DTYPE, name)
    record = np.zeros(1, TELEMETRY_DTYPE)
    for value in range(1, count + 1):
        _stamp(record, value)
        seqlock.write(record)
    seqlock.close()


def _write_ring(name: str, capacity: int, count: int, pause_every: int) -> None:
    ring = SharedRing(TELEMETRY_DTYPE, capacity, name)
    record = np.zeros(1, TELEMETRY_DTYPE)
    for value in range(count):
        _stamp(record, value)
        ring.push(record)
        if value % pause_every == 0:
            time.sleep(0)
    ring.close()


def _spawn(target: object, *args: object) -> multiprocessing.process.BaseProcess:
    process = multiprocessing.get_context("spawn").Process(target=target, args=args)
    process.start()
    return process


@pytest.mark.slow
def test_seqlock_reader_never_sees_a_torn_record_while_another_process_writes() -> None:
    seqlock = Seqlock(TELEMETRY_DTYPE)
    writer = _spawn(_write_state, seqlock.name, 30_000)
    reads, last = 0, 0
    try:
        while writer.is_alive() or reads == 0:
            snapshot = seqlock.read()
            assert _consistent(snapshot), f"torn read: {snapshot['tick']}"
            assert snapshot["tick"][0] >= last  # never goes back in time
            last = int(snapshot["tick"][0])
            reads += 1
    finally:
        writer.join(30)
        seqlock.close()
    assert writer.exitcode == 0 and reads > 100 and last == 30_000


def test_unprotected_copies_do_tear_so_the_check_above_can_fail() -> None:
    """Without the sequence check, a copy taken mid-write mixes two records: `_consistent` catches it."""
    record = np.zeros(1, TELEMETRY_DTYPE)
    _stamp(record, 1)
    torn = record.copy()
    torn["slider_command_m"] = 2.0  # as if the writer had got halfway
    assert _consistent(record) and not _consistent(torn)


@pytest.mark.slow
def test_ring_drains_every_record_in_order_without_tearing_and_counts_losses() -> None:
    ring = SharedRing(TELEMETRY_DTYPE, 256)
    total = 30_000
    writer = _spawn(_write_ring, ring.name, 256, total, 64)
    seen: list[np.ndarray] = []
    try:
        while writer.is_alive():
            batch = ring.drain()
            assert _consistent(batch)
            seen.append(batch["tick"])
        seen.append(ring.drain()["tick"])
    finally:
        writer.join(30)
        ring.close()
    ticks = np.concatenate(seen)
    assert writer.exitcode == 0
    assert np.all(np.diff(ticks) > 0)  # in order, no duplicates
    assert len(ticks) + ring.lost == total  # every record either delivered whole or counted as lost
    assert ticks[-1] == total - 1


def test_ring_reports_what_a_slow_reader_lost() -> None:
    ring = SharedRing(TELEMETRY_DTYPE, 8)
    record = np.zeros(1, TELEMETRY_DTYPE)
    try:
        for value in range(20):
            _stamp(record, value)
            ring.push(record)
        drained = ring.drain()
        # The slot the producer would write next is the oldest one; it is dropped as possibly torn.
        assert list(drained["tick"]) == list(range(13, 20)) and ring.lost == 13
        assert len(ring.drain()) == 0
    finally:
        ring.close()


def test_ring_capacity_must_be_a_power_of_two() -> None:
    with pytest.raises(ValueError, match="capacity"):
        SharedRing(TELEMETRY_DTYPE, 100)


# --- the memory model: barriers and the CPU guard ------------------------------------------------------


@pytest.mark.parametrize("machine", ["x86_64", "AMD64", "aarch64", "arm64"])
def test_seqlock_starts_on_cpus_whose_8_byte_stores_are_atomic(machine: str) -> None:
    shm.require_supported_cpu(machine)


@pytest.mark.parametrize("machine", ["armv7l", "i686", "riscv64", "ppc64le", ""])
def test_seqlock_refuses_an_unsupported_cpu_naming_it_and_creates_nothing(
    machine: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    with pytest.raises(shm.UnsupportedPlatformError, match=f"cpu = '{machine}'.*supported CPUs are"):
        shm.require_supported_cpu(machine)
    monkeypatch.setattr(shm.platform, "machine", lambda: machine)
    created: list[object] = []
    monkeypatch.setattr(shm, "SharedBlock", lambda *args: created.append(args))
    with pytest.raises(shm.UnsupportedPlatformError):
        Seqlock(TELEMETRY_DTYPE)
    assert created == []  # refused before any shared memory exists


def test_memory_barrier_is_a_hardware_fence() -> None:
    shm.memory_barrier()
    fresh = numba.njit(cache=False)(shm.memory_barrier.py_func)  # the cached one keeps no IR to inspect
    fresh()
    (signature,) = fresh.signatures
    assert "fence seq_cst" in fresh.inspect_llvm(signature)


def test_seqlock_fences_the_record_copy_from_both_sequence_updates(monkeypatch: pytest.MonkeyPatch) -> None:
    """At each barrier of a write: the sequence is already odd, and the record is old at the first, new
    at the second; a reader fences between its sequence reads and its copy the same way."""
    seqlock = Seqlock(TELEMETRY_DTYPE)
    old, new = np.zeros(1, TELEMETRY_DTYPE), np.zeros(1, TELEMETRY_DTYPE)
    _stamp(old, 1)
    _stamp(new, 2)
    try:
        seqlock.write(old)
        seen: list[tuple[int, int]] = []
        monkeypatch.setattr(
            shm, "memory_barrier", lambda: seen.append((seqlock.sequence, int(seqlock._record["tick"][0])))
        )
        seqlock.write(new)
        assert seen == [(3, 1), (3, 2)]
        seen.clear()
        assert seqlock.read()["tick"][0] == 2
        assert seen == [(4, 2), (4, 2)]
    finally:
        seqlock.close()
