"""Shared memory between the worker and the service: a seqlock for the latest state and SPSC rings.

Seqlock (one writer, many readers): the writer makes the sequence odd, copies the record, makes it
even again; a reader copies the record between two reads of the sequence and retries if they differ
or are odd, so it never returns a torn record. Ring (one writer, one reader): the writer never waits:
it writes slot `count % capacity` and only then publishes `count + 1`. The reader copies what was
published and afterwards drops every record the writer may have lapped while it was copying, and
counts them as lost. Both rely on aligned 8-byte stores being atomic and stores becoming visible in
program order (x86-64 TSO); the sequence and count words sit at offset 0 of page-aligned blocks.

The creating process (the service side) owns the names and unlinks them; the worker attaches by name
through /dev/shm so that Python's resource tracker never unlinks blocks it did not create.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import time
from multiprocessing import shared_memory

import numpy as np

_HEADER_BYTES = 64  # keeps the payload 8-byte aligned and the counters on their own cache line


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


class Seqlock:
    """The latest record of `dtype`, written by one process and read without tearing by others."""

    def __init__(self, dtype: np.dtype, name: str | None = None) -> None:
        self.dtype = dtype
        self.block = SharedBlock(_HEADER_BYTES + dtype.itemsize, name)
        self._sequence = np.ndarray((1,), np.uint64, self.block.buffer, 0)
        self._record = np.ndarray((1,), dtype, self.block.buffer, _HEADER_BYTES)
        self._copy = np.zeros(1, dtype)

    @property
    def name(self) -> str:
        return self.block.name

    def write(self, record: np.ndarray) -> None:
        """Publish `record` (a (1,) array of `dtype`); allocation-free."""
        self._sequence[0] += np.uint64(1)
        self._record[:] = record
        self._sequence[0] += np.uint64(1)

    def read(self, timeout_s: float = 2.0) -> np.ndarray:
        """A consistent copy of the latest record, shape (1,).

        A writer descheduled mid-write holds readers off; yield the CPU now and then so that it can finish.
        """
        deadline = time.monotonic() + timeout_s
        attempts = 0
        while True:
            before = int(self._sequence[0])
            if not before & 1:
                self._copy[:] = self._record
                if int(self._sequence[0]) == before:
                    return self._copy.copy()
            attempts += 1
            if attempts % 64 == 0:
                if time.monotonic() > deadline:
                    raise TimeoutError("seqlock: no consistent snapshot (is the writer stuck mid-write?)")
                time.sleep(0)

    @property
    def sequence(self) -> int:
        return int(self._sequence[0])

    def close(self) -> None:
        del self._sequence, self._record
        self.block.close()


class SharedRing:
    """A single-producer single-consumer ring of `dtype` records that never blocks the producer."""

    def __init__(self, dtype: np.dtype, capacity: int, name: str | None = None) -> None:
        if capacity < 2 or capacity & (capacity - 1):
            raise ValueError(f"capacity = {capacity}: must be a power of two >= 2")
        self.dtype, self.capacity = dtype, capacity
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

    def slot(self) -> np.ndarray:
        """The producer's next slot as a (1,) view, to fill in place before `publish()`."""
        index = int(self._written[0]) & self._mask
        return self._records[index : index + 1]

    def publish(self) -> None:
        self._written[0] += np.uint64(1)

    def push(self, record: np.ndarray) -> None:
        """Copy one record in and publish it; allocation-free apart from the slot view."""
        self.slot()[:] = record
        self.publish()

    def drain(self, max_records: int | None = None) -> np.ndarray:
        """Every record published since the last drain (oldest first), none torn."""
        written = int(self._written[0])
        start = max(self.read_count, written - self.capacity)
        if max_records is not None:
            written = min(written, start + max_records)
        indices = np.arange(start, written) & self._mask
        copied = self._records[indices]  # fancy indexing copies
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
        self.block = SharedBlock(_HEADER_BYTES + CONTROL_DTYPE.itemsize, name)
        self.fields = np.ndarray((1,), CONTROL_DTYPE, self.block.buffer, _HEADER_BYTES)

    @property
    def name(self) -> str:
        return self.block.name

    def request_estop(self, request_ns: int) -> None:
        # Time first, then the counter: a reader that sees the new count also sees its time (TSO).
        self.fields["estop_request_ns"] = request_ns
        self.fields["estop_requests"] += np.uint64(1)

    def close(self) -> None:
        del self.fields
        self.block.close()
