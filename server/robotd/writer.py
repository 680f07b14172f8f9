"""The daemon's database writer: one non-real-time thread that applies every write of the daemon in
order (run starts, commands, ends, events, telemetry chunks). A caller that needs the result waits for
it; background writes (telemetry, events) are retried until the database takes them, and the run's
journal holds them meanwhile."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, TypeVar

from sqlalchemy.orm import Session

from server.db import Database

log = logging.getLogger("ssp_rehab.robotd")
T = TypeVar("T")
RETRY_BACKOFF_S = (0.2, 0.5, 1.0, 2.0, 5.0)


class DatabaseWriter:
    def __init__(self, database: Database) -> None:
        self.database = database
        self._queue: queue.Queue[tuple[Callable[[Session], Any], Future[Any], bool] | None] = queue.Queue()
        self._thread = threading.Thread(target=self._run, name="robotd-db-writer", daemon=True)
        self.failures = 0
        self.last_error: str | None = None

    def start(self) -> None:
        self._thread.start()

    def submit(self, write: Callable[[Session], T], *, retry: bool) -> Future[T]:
        """Queue `write(session)`; with `retry`, it is tried again (with backoff) until it succeeds."""
        future: Future[T] = Future()
        self._queue.put((write, future, retry))
        return future

    def call(self, write: Callable[[Session], T], timeout_s: float = 60.0) -> T:
        """Apply `write` after everything queued before it, and return its result (or raise its error)."""
        return self.submit(write, retry=False).result(timeout_s)

    def drain(self, timeout_s: float = 30.0) -> None:
        """Wait until everything queued so far is written."""
        self.submit(lambda _session: None, retry=False).result(timeout_s)

    def stop(self, timeout_s: float = 30.0) -> None:
        self._queue.put(None)
        self._thread.join(timeout_s)

    def _run(self) -> None:
        while (item := self._queue.get()) is not None:
            write, future, retry = item
            attempt = 0
            while True:
                try:
                    with self.database.session() as session:
                        future.set_result(write(session))
                    break
                except Exception as error:
                    self.failures += 1
                    self.last_error = f"{type(error).__name__}: {error}".splitlines()[0][:300]
                    if not retry:
                        future.set_exception(error)
                        break
                    log.warning("database write failed (attempt %d), will retry: %s", attempt + 1, self.last_error)
                    time.sleep(RETRY_BACKOFF_S[min(attempt, len(RETRY_BACKOFF_S) - 1)])
                    attempt += 1
