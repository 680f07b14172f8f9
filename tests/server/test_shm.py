"""Seqlock and telemetry ring: a reader in another process never sees a torn record."""

from __future__ import annotations

import mmap
import multiprocessing
import resource
import time
from typing import Any

import numba
import numpy as np
import pytest

from server.realtime import shm
from server.realtime.shm import ControlBlock, Seqlock, SharedRing
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


def _page_faults_of_a_first_lap(prepared: bool) -> int:
    """Minor page faults this process takes while it produces the first lap of a fresh ring, attached by
    name the way the worker attaches the ring its client created."""
    created = SharedRing(TELEMETRY_DTYPE, 4096)
    producer = SharedRing(TELEMETRY_DTYPE, 4096, created.name)
    record = np.zeros(1, TELEMETRY_DTYPE)
    try:
        if prepared:
            producer.prepare_to_produce()
        producer.push(record)  # the interpreter's own first-call work, not the ring's
        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for value in range(1, 4096):
            _stamp(record, value)
            producer.push(record)
        faults = resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before
        assert list(created.drain()["tick"][-3:]) == [4093, 4094, 4095]
        return faults
    finally:
        producer.close()
        created.close()


def test_a_prepared_producer_takes_no_page_fault_in_its_first_lap() -> None:
    """The worker maps its rings' pages before the loop: a fault inside a tick allocates a page (issue 20)."""
    pages = 4096 * TELEMETRY_DTYPE.itemsize // mmap.PAGESIZE
    assert _page_faults_of_a_first_lap(prepared=False) >= pages // 2  # the test can fail: unprepared rings fault
    assert _page_faults_of_a_first_lap(prepared=True) <= pages // 20


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


def _fresh_llvm(dispatcher: object, *args: object) -> str:
    """LLVM IR of a fresh compile (a function loaded from numba's cache keeps no IR to inspect)."""
    fresh = numba.njit(cache=False)(dispatcher.py_func)  # type: ignore[attr-defined]
    fresh(*args)
    (signature,) = fresh.signatures
    return fresh.inspect_llvm(signature)


def test_memory_barrier_is_a_hardware_fence() -> None:
    assert "fence seq_cst" in _fresh_llvm(shm.memory_barrier)


def test_seqlock_write_and_read_each_fence_the_copy_from_both_sequence_accesses() -> None:
    """Two full barriers in each compiled half of the seqlock, with the copy between them."""
    sequence, record, source = np.zeros(1, np.uint64), np.zeros(16, np.uint8), np.arange(16, dtype=np.uint8)
    for function in (shm._seqlock_write, shm._seqlock_try_read):
        ir = _fresh_llvm(function, sequence, record, source)
        assert ir.count("fence seq_cst") == 2, function
        first, second = ir.index("fence seq_cst"), ir.rindex("fence seq_cst")
        between = ir[first:second]
        assert "memcpy" in between or "memmove" in between or "store i8" in between  # the record copy


def test_seqlock_publishes_later_changes_of_the_same_record_and_refuses_a_foreign_one() -> None:
    seqlock = Seqlock(TELEMETRY_DTYPE)
    record = np.zeros(1, TELEMETRY_DTYPE)
    try:
        for value in (1, 2):
            _stamp(record, value)
            seqlock.write(record)  # the same array again: its new contents are published
            snapshot = seqlock.read()
            assert _consistent(snapshot) and snapshot["tick"][0] == value
        assert seqlock.sequence == 4
        with pytest.raises(ValueError, match="expected a contiguous"):
            seqlock.write(np.zeros(2, TELEMETRY_DTYPE))
        assert seqlock.sequence == 4  # nothing half-written
    finally:
        seqlock.close()


@pytest.mark.parametrize(
    "make", [lambda: SharedRing(TELEMETRY_DTYPE, 8), lambda: ControlBlock()], ids=["ring", "control"]
)
def test_ring_and_control_block_refuse_an_unsupported_cpu_and_create_nothing(
    make: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(shm.platform, "machine", lambda: "armv7l")
    created: list[object] = []
    monkeypatch.setattr(shm, "SharedBlock", lambda *args: created.append(args))
    with pytest.raises(shm.UnsupportedPlatformError):
        make()
    assert created == []


def test_the_ring_fences_its_slot_before_publishing_and_its_copy_from_both_count_reads(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    ring = SharedRing(TELEMETRY_DTYPE, 8)
    seen: list[int] = []
    monkeypatch.setattr(shm, "memory_barrier", lambda: seen.append(ring.written))
    try:
        record = np.zeros(1, TELEMETRY_DTYPE)
        _stamp(record, 7)
        ring.push(record)
        assert seen == [0] and ring.written == 1  # the fence came after the slot, before the count
        seen.clear()
        drained = ring.drain()
        assert len(seen) == 2 and drained["tick"].tolist() == [7]  # count, fence, copy, fence, count
    finally:
        ring.close()


def test_the_estop_request_fences_its_time_before_its_counter(monkeypatch: pytest.MonkeyPatch) -> None:
    control = ControlBlock()
    seen: list[tuple[int, int]] = []
    fields = control.fields
    monkeypatch.setattr(
        shm,
        "memory_barrier",
        lambda: seen.append((int(fields["estop_request_ns"][0]), int(fields["estop_requests"][0]))),
    )
    try:
        control.request_estop(123_456)
        assert seen == [(123_456, 0)] and int(fields["estop_requests"][0]) == 1
    finally:
        control.close()
