"""Shared memory between the worker and the service: a seqlock for the latest state and SPSC rings.

Seqlock (one writer, many readers): the writer makes the sequence odd, copies the record, makes it
even again; a reader copies the record between two reads of the sequence and retries if they differ
or are odd, so it never returns a torn record. The seqlock does not trust the CPU's store order: a full
memory barrier (`memory_barrier`, an LLVM `fence seq_cst` compiled by numba: `lock or` on x86-64,
`dmb ish` on ARM64) separates each sequence update from the record copy on both sides, which is what the
weakly ordered ARM memory model needs. It still needs aligned 8-byte stores to be single-copy atomic,
so it refuses to start on a CPU not known to give that (`require_supported_cpu`: x86-64 and 64-bit ARM).
Ring (one writer, one reader): the writer never waits: it writes slot `count % capacity` and only then
publishes `count + 1`. The reader copies what was published and afterwards drops every record the
writer may have lapped while it was copying, and counts them as lost. The same barrier orders the ring
(slot before count on the writer's side; count, copy, count again on the reader's) and the control
block's emergency-stop request (its time before its counter), so neither relies on x86-64's store order;
the sequence and count words sit at offset 0 of page-aligned blocks.

The creating process (the service side) owns the names and unlinks them; the worker attaches by name
through /dev/shm so that Python's resource tracker never unlinks blocks it did not create.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import platform
import time
from collections.abc import Callable
from multiprocessing import shared_memory
from typing import Any, cast

import numba
import numpy as np
from numba.core import types
from numba.extending import intrinsic

_HEADER_BYTES = 64  # keeps the payload 8-byte aligned and the counters on their own cache line


# CPUs (platform.machine() names) on which an aligned 8-byte store is single-copy atomic, so that the
# fenced seqlock is correct: x86-64 (TSO) and 64-bit ARM (weakly ordered: the barriers make it correct).
SEQLOCK_CPUS = frozenset({"x86_64", "amd64", "aarch64", "arm64"})


class UnsupportedPlatformError(RuntimeError):
    """The shared-memory seqlock cannot be trusted on this CPU."""


def require_supported_cpu(machine: str | None = None) -> None:
    """Refuse to share state on a CPU whose memory model the seqlock was not made for (32-bit ARM, for
    one, may split an 8-byte store and tear the sequence word)."""
    machine = platform.machine() if machine is None else machine
    if machine.lower() not in SEQLOCK_CPUS:
        raise UnsupportedPlatformError(
            f"cpu = {machine!r}: the shared-memory seqlock needs atomic aligned 8-byte stores; supported CPUs "
            f"are {sorted(SEQLOCK_CPUS)}. Run the console and the robot worker on one of them."
        )


@intrinsic
def _fence(typingctx: object) -> tuple[object, object]:
    def codegen(context: Any, builder: Any, signature: object, args: object) -> object:
        builder.fence("seq_cst")
        return context.get_dummy_value()

    return types.void(), codegen


# The intrinsic as compiled code calls it (numba supplies the typing context), for the type checker.
_full_fence = cast(Callable[[], None], _fence)


@numba.njit(cache=True)
def memory_barrier() -> None:
    """A full hardware memory barrier: no load or store crosses it, in the compiler or in the CPU."""
    _full_fence()


class SharedBlock:
    """A named shared-memory block, created here or attached by name."""

    def __init__(self, size: int, name: str | None = None) -> None:
        self._owner = name is None
        self._shm: shared_memory.SharedMemory | None = None
        self._mmap: mmap.mmap | None = None
        if self._owner:
            self._shm = shared_memory.SharedMemory(create=True, size=size)
            self.name = self._shm.name
            assert self._shm.buf is not None
            self.buffer: memoryview = self._shm.buf
        else:
            assert name is not None
            descriptor = os.open(f"/dev/shm/{name.lstrip('/')}", os.O_RDWR)
            try:
                self._mmap = mmap.mmap(descriptor, size)
            finally:
                os.close(descriptor)
            self.name = name
            self.buffer = memoryview(self._mmap)

    def close(self) -> None:
        """Unmap (and unlink, for the creator). Arrays viewing the block must be dropped first."""
        self.buffer.release()
        if self._shm is not None:
            self._shm.close()
            if self._owner:
                with contextlib.suppress(FileNotFoundError):
                    self._shm.unlink()
        if self._mmap is not None:
            self._mmap.close()


@numba.njit(cache=True)
def _seqlock_write(sequence: np.ndarray, record_bytes: np.ndarray, source_bytes: np.ndarray) -> None:
    sequence[0] = sequence[0] + np.uint64(1)  # odd: a write is under way
    _full_fence()  # readers see the odd sequence before any byte of the new record ...
    record_bytes[:] = source_bytes
    _full_fence()  # ... and every byte of it before the even sequence
    sequence[0] = sequence[0] + np.uint64(1)


@numba.njit(cache=True)
def _seqlock_try_read(sequence: np.ndarray, record_bytes: np.ndarray, copy_bytes: np.ndarray) -> bool:
    """One attempt: True when the copy lies between two reads of the same even sequence."""
    before = sequence[0]
    if before & np.uint64(1):
        return False
    _full_fence()  # the copy is not read ahead of the first sequence read ...
    copy_bytes[:] = record_bytes
    _full_fence()  # ... nor behind the second
    return sequence[0] == before


def load_kernels() -> None:
    """Load this module's compiled kernels (from numba's cache, or compile them) now, with the argument types
    the blocks use. A process that attaches a worker's blocks only later (the stop listener starts before the
    worker) would otherwise load them inside its first emergency stop: 200 ms, measured."""
    memory_barrier()
    buffer = memoryview(bytearray(_HEADER_BYTES + 8))
    sequence = np.ndarray((1,), np.uint64, buffer, 0)
    record_bytes = np.ndarray((8,), np.uint8, buffer, _HEADER_BYTES)
    _seqlock_try_read(sequence, record_bytes, np.zeros(8, np.uint8))
    _seqlock_write(np.zeros(1, np.uint64), np.zeros(8, np.uint8), record_bytes)


class Seqlock:
    """The latest record of `dtype`, written by one process and read without tearing by others.

    Each write and each read attempt is one compiled call: the sequence updates, the two barriers and the
    byte copy of the record together (a structured numpy copy alone costs several µs)."""

    def __init__(self, dtype: np.dtype, name: str | None = None) -> None:
        require_supported_cpu()
        self.dtype = dtype
        self.block = SharedBlock(_HEADER_BYTES + dtype.itemsize, name)
        self._sequence = np.ndarray((1,), np.uint64, self.block.buffer, 0)
        self._record_bytes = np.ndarray((dtype.itemsize,), np.uint8, self.block.buffer, _HEADER_BYTES)
        self._copy = np.zeros(1, dtype)
        self._copy_bytes = self._copy.view(np.uint8)
        self._source: np.ndarray | None = None
        self._source_bytes = np.zeros(dtype.itemsize, np.uint8)
        load_kernels()  # now, never inside the first tick's write

    @property
    def name(self) -> str:
        return self.block.name

    def write(self, record: np.ndarray) -> None:
        """Publish `record` (a (1,) array of `dtype`); allocation-free when the same array is published
        again (the worker's telemetry record)."""
        if record is not self._source:
            if record.dtype != self.dtype or record.shape != (1,) or not record.flags.c_contiguous:
                raise ValueError(
                    f"seqlock record: {record.dtype} {record.shape}, expected a contiguous (1,) {self.dtype}"
                )
            self._source, self._source_bytes = record, record.view(np.uint8)  # a view: later changes publish
        _seqlock_write(self._sequence, self._record_bytes, self._source_bytes)

    def read(self, timeout_s: float = 2.0) -> np.ndarray:
        """A consistent copy of the latest record, shape (1,).

        A writer descheduled mid-write holds readers off; yield the CPU now and then so that it can finish.
        """
        deadline = time.monotonic() + timeout_s
        attempts = 0
        while not _seqlock_try_read(self._sequence, self._record_bytes, self._copy_bytes):
            attempts += 1
            if attempts % 64 == 0:
                if time.monotonic() > deadline:
                    raise TimeoutError("seqlock: no consistent snapshot (is the writer stuck mid-write?)")
                time.sleep(0)
        return self._copy_bytes.copy().view(self.dtype)  # a byte copy: much faster than a structured one

    @property
    def sequence(self) -> int:
        return int(self._sequence[0])

    def close(self) -> None:
        del self._sequence, self._record_bytes
        self.block.close()


class SharedRing:
    """A single-producer single-consumer ring of `dtype` records that never blocks the producer."""

    def __init__(self, dtype: np.dtype, capacity: int, name: str | None = None) -> None:
        if capacity < 2 or capacity & (capacity - 1):
            raise ValueError(f"capacity = {capacity}: must be a power of two >= 2")
        self.dtype, self.capacity = dtype, capacity
        require_supported_cpu()
        memory_barrier()  # compiled before the first publish, not inside a tick
        self.block = SharedBlock(_HEADER_BYTES + dtype.itemsize * capacity, name)
        self._written = np.ndarray((1,), np.uint64, self.block.buffer, 0)  # producer's count, published
        self._records = np.ndarray((capacity,), dtype, self.block.buffer, _HEADER_BYTES)
        self._mask = capacity - 1
        self.read_count = 0  # consumer side only
        self.lost = 0  # records the consumer never saw because the producer lapped it

    @property
    def name(self) -> str:
        return self.block.name

    @property
    def written(self) -> int:
        return int(self._written[0])

    def prepare_to_produce(self) -> None:
        """Map every page of the ring into the producer, writable, before its first publish: its first lap
        then takes no page fault inside a tick (the worker's telemetry ring: about 190 a second for its first
        31 s at 1 kHz, measured). Each page gets back the byte it holds: nothing published changes."""
        pages = np.ndarray((len(self.block.buffer),), np.uint8, self.block.buffer)
        pages[:: mmap.PAGESIZE] = pages[:: mmap.PAGESIZE].copy()

    def slot(self) -> np.ndarray:
        """The producer's next slot as a (1,) view, to fill in place before `publish()`."""
        index = int(self._written[0]) & self._mask
        return self._records[index : index + 1]

    def publish(self) -> None:
        memory_barrier()  # the slot's contents become visible before the count that publishes them
        self._written[0] += np.uint64(1)

    def push(self, record: np.ndarray) -> None:
        """Copy one record in and publish it; allocation-free apart from the slot view."""
        self.slot()[:] = record
        self.publish()

    def drain(self, max_records: int | None = None) -> np.ndarray:
        """Every record published since the last drain (oldest first), none torn."""
        written = int(self._written[0])
        memory_barrier()  # read the slots only after the count that published them
        start = max(self.read_count, written - self.capacity)
        if max_records is not None:
            written = min(written, start + max_records)
        indices = np.arange(start, written) & self._mask
        copied = self._records[indices]  # fancy indexing copies
        memory_barrier()  # finish the copy before asking how far the producer has come since
        # The producer may have lapped us while we copied: the records it could have been overwriting
        # (up to and including the one it is writing now) are not trustworthy, so drop them.
        lapped_to = int(self._written[0]) - self.capacity + 1
        valid_from = min(max(start, lapped_to), written)
        self.lost += valid_from - self.read_count
        self.read_count = written
        return copied[max(0, valid_from - start) :]

    def close(self) -> None:
        del self._written, self._records
        self.block.close()


CONTROL_DTYPE = np.dtype(
    [
        ("estop_requests", np.uint64),  # bumped by the client; a change means "emergency stop now"
        ("estop_request_ns", np.int64),  # perf_counter_ns (CLOCK_MONOTONIC) of the latest request
        ("worker_pid", np.int64),
        ("worker_ready", np.uint64),
        ("service_beats", np.uint64),  # advanced by the service's heartbeat thread (server.realtime.heartbeat)
        ("relay_beats", np.uint64),  # advanced by the heartbeat relay; the worker's watchdog watches this
    ]
)


class ControlBlock:
    """Flags that must not queue behind anything: the emergency-stop request and the worker's liveness."""

    def __init__(self, name: str | None = None) -> None:
        require_supported_cpu()
        load_kernels()  # now, never inside the first emergency stop
        self.block = SharedBlock(_HEADER_BYTES + CONTROL_DTYPE.itemsize, name)
        self.fields = np.ndarray((1,), CONTROL_DTYPE, self.block.buffer, _HEADER_BYTES)

    @property
    def name(self) -> str:
        return self.block.name

    def request_estop(self, request_ns: int) -> None:
        # Time first, then the counter: a reader that sees the new count also sees its time.
        self.fields["estop_request_ns"] = request_ns
        memory_barrier()
        self.fields["estop_requests"] += np.uint64(1)

    def estop_request(self) -> tuple[int, float | None]:
        """(emergency stops requested so far, UTC of the latest request). The request's time is monotonic
        (perf_counter_ns, one clock for every process), converted with the current offset to wall time."""
        requests = int(self.fields["estop_requests"][0])
        memory_barrier()  # the counter before its time: the time read belongs to this count or a later one
        if not requests:
            return 0, None
        request_ns = int(self.fields["estop_request_ns"][0])
        return requests, time.time() - (time.perf_counter_ns() - request_ns) * 1e-9

    def close(self) -> None:
        del self.fields
        self.block.close()
