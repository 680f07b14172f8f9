"""What `/health` says about the database (issue 20, defect 7): a pooled `SELECT 1`, bounded by a short
timeout, its result cached so that /health under load asks the database at most once per
`PROBE_CACHE_S` per web process, and one probe in flight at a time (a hung database holds one thread)."""

from __future__ import annotations

import logging
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout

from sqlalchemy import text

from server.db import Database

logger = logging.getLogger(__name__)

PROBE_CACHE_S = 2.0
PROBE_TIMEOUT_S = 1.0
UNREACHABLE = "the database is unreachable"  # no host, port or file: /health is public


class DatabaseProbe:
    def __init__(self, cache_s: float = PROBE_CACHE_S, timeout_s: float = PROBE_TIMEOUT_S) -> None:
        self.cache_s, self.timeout_s = cache_s, timeout_s
        self._lock = threading.Lock()
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="health-database-probe")
        self._probe: Future[None] | None = None
        self._result: str | None = None  # None: it answered
        self._checked_s = -float("inf")

    def unreachable_reason(self, database: Database) -> str | None:
        """None when the database answered `SELECT 1` within the last `cache_s`; else why not."""
        with self._lock:
            if time.monotonic() - self._checked_s <= self.cache_s:
                return self._result
            if self._probe is None:
                self._probe = self._executor.submit(self._select_one, database)
            probe = self._probe
        try:
            probe.result(self.timeout_s)
        except FutureTimeout:
            reason = f"{UNREACHABLE}: no answer within {self.timeout_s:g} s"
            self._remember(probe, reason, done=False)
            return reason
        except Exception as error:
            logger.warning("health check: the database did not answer SELECT 1: %s", error)
            self._remember(probe, UNREACHABLE, done=True)
            return UNREACHABLE
        self._remember(probe, None, done=True)
        return None

    def _remember(self, probe: Future[None], reason: str | None, *, done: bool) -> None:
        with self._lock:
            self._result, self._checked_s = reason, time.monotonic()
            if done and self._probe is probe:
                self._probe = None
            elif not done:  # still hanging: the next check after the cache waits on the same probe
                probe.add_done_callback(lambda finished: self._finished(finished))

    def _finished(self, probe: Future[None]) -> None:
        with self._lock:
            if self._probe is probe:
                self._probe = None

    @staticmethod
    def _select_one(database: Database) -> None:
        with database.session() as session:
            session.execute(text("SELECT 1"))
