"""Login throttling with the `limits` library, its counters kept in the database so that every web process
and every console on the same database shares them (issue 15 §3).

Two measures, so that the throttle can never be turned against a clinician (issue 20, defect 17):

- **The address backs off.** Failures from one client address (any name, known or not) have tiers that
  back off: `max_failures` within `window_s`, then twice as many within four times the window, and so on;
  past a tier the address gets 429 with Retry-After. The address is the connecting one; X-Forwarded-For is
  believed only from `trusted_proxies` (server.app), so a header cannot aim the lock at someone else. An
  attempt takes its slots *before* the password is checked and keeps them when it is wrong, so parallel
  guesses cannot outrun the count (one atomic upsert); a success gives them back.
- **The account slows down, never locks.** Failures on one account (or one unknown name: the same timing,
  so a name's existence does not show) from any address count within four windows; past `max_failures`
  each attempt on it waits 1 s, 2 s, 4 s … up to `delay_max_s` before its password is checked. Guessing
  from many addresses is slowed; the right password still gets in, from any address that is not itself
  backing off. A success clears the account's count.

An admin lifts either (`POST /api/v1/auth/unlock`, `ssp-rehab unlock-login`).
"""

from __future__ import annotations

import asyncio
import hashlib
import math
import time
from collections.abc import Awaitable, Callable, Sequence
from typing import cast

from limits import RateLimitItem, RateLimitItemPerSecond
from limits.storage import Storage
from limits.strategies import FixedWindowRateLimiter
from sqlalchemy import case, delete, select
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.exc import SQLAlchemyError
from sqlalchemy.orm import Session

from server.auth.models import RateLimitCounter
from server.db import write_transaction

Bucket = tuple[str, str]  # (kind, identifier): ("account", "17"), ("address", "10.0.0.5"), ("name", <digest>)
BACKOFF_TIERS = 3
DELAY_MAX_S = 10.0
_COUNTERS = RateLimitCounter


class DatabaseStorage(Storage):
    """A `limits` storage on the service's database (SQLite or PostgreSQL) through one ORM session.

    `incr` is a single INSERT … ON CONFLICT DO UPDATE … RETURNING, atomic on both backends (PostgreSQL
    locks the row; SQLite's writer lock is taken up front by `write_transaction`). Only fixed windows."""

    STORAGE_SCHEME = None  # built per request around the request's session, never from a URI

    def __init__(self, session: Session, clock: Callable[[], float] = time.time) -> None:
        super().__init__()
        self._session = session
        self._clock = clock

    @property
    def base_exceptions(self) -> type[Exception] | tuple[type[Exception], ...]:
        return SQLAlchemyError

    def incr(self, key: str, expiry: int, amount: int = 1) -> int:
        now = self._clock()
        dialect = self._session.get_bind().dialect.name
        insert = postgresql.insert(_COUNTERS) if dialect == "postgresql" else sqlite.insert(_COUNTERS)
        fresh_count = max(amount, 0)
        expired = _COUNTERS.expires_at <= now
        added = _COUNTERS.count + amount
        statement = (
            insert.values(key=key, count=fresh_count, expires_at=now + expiry)
            .on_conflict_do_update(
                index_elements=[_COUNTERS.key],
                set_={
                    "count": case((expired, fresh_count), (added < 0, 0), else_=added),
                    "expires_at": case((expired, now + expiry), else_=_COUNTERS.expires_at),
                },
            )
            .returning(_COUNTERS.count)
        )
        with write_transaction(self._session):
            count = int(self._session.execute(statement).scalar_one())
            if count == fresh_count:  # a new window: a good moment to drop the windows that have ended
                self._session.execute(delete(_COUNTERS).where(_COUNTERS.expires_at <= now))
        return count

    def _row(self, key: str) -> tuple[int, float] | None:
        row = self._session.execute(select(_COUNTERS.count, _COUNTERS.expires_at).where(_COUNTERS.key == key)).first()
        self._session.commit()  # end the read transaction: it must not pin a snapshot (or SQLite's WAL)
        if row is None or row[1] <= self._clock():
            return None
        return int(row[0]), float(row[1])

    def get(self, key: str) -> int:
        row = self._row(key)
        return 0 if row is None else row[0]

    def get_expiry(self, key: str) -> float:
        row = self._row(key)
        return self._clock() if row is None else row[1]

    def check(self) -> bool:
        try:
            self._session.execute(select(1))
        except SQLAlchemyError:
            return False
        return True

    def reset(self) -> int | None:
        with write_transaction(self._session):
            result = self._session.execute(delete(_COUNTERS))
            return cast(int, getattr(result, "rowcount", 0))

    def clear(self, key: str) -> None:
        with write_transaction(self._session):
            self._session.execute(delete(_COUNTERS).where(_COUNTERS.key == key))

    def clear_prefix(self, prefix: str) -> None:
        with write_transaction(self._session):
            self._session.execute(delete(_COUNTERS).where(_COUNTERS.key.startswith(prefix, autoescape=True)))


def account_bucket(user_id: int) -> Bucket:
    return ("account", str(user_id))


def unknown_name_bucket(username: str) -> Bucket:
    # A digest: the typed name may be long or odd, and it need not be readable in the table.
    return ("name", hashlib.sha256(username.lower().encode()).hexdigest()[:32])


def address_bucket(address: str) -> Bucket:
    return ("address", address)


class LoginThrottle:
    def __init__(
        self,
        max_failures: int,
        window_s: float,
        *,
        delay_max_s: float = DELAY_MAX_S,
        tiers: int = BACKOFF_TIERS,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.max_failures = max_failures
        self.window_s = window_s
        self.delay_max_s = delay_max_s
        self.clock = clock
        self.sleep: Callable[[float], Awaitable[None]] = asyncio.sleep  # how a delay is waited for
        window = max(1, math.ceil(window_s))
        self.limits: list[RateLimitItem] = [
            RateLimitItemPerSecond(max_failures * 2**tier, window * 4**tier, namespace="login") for tier in range(tiers)
        ]
        # Counts an account's failures only; never refuses (the amount is far beyond any count).
        self.account_failures = RateLimitItemPerSecond(2**31, window * 4, namespace="login-delay")

    def _limiter(self, session: Session) -> tuple[FixedWindowRateLimiter, DatabaseStorage]:
        storage = DatabaseStorage(session, lambda: self.clock())
        return FixedWindowRateLimiter(storage), storage

    def reserve(self, session: Session, buckets: Sequence[Bucket]) -> float | None:
        """Take a slot for one login attempt in every tier of `buckets`; None when the attempt may go ahead,
        else the seconds until it may (and nothing is taken)."""
        limiter, storage = self._limiter(session)
        taken: list[tuple[RateLimitItem, Bucket]] = []
        for bucket in buckets:
            for limit in self.limits:
                taken.append((limit, bucket))
                if not limiter.hit(limit, *bucket):
                    for item, held in taken:
                        storage.incr(item.key_for(*held), item.get_expiry(), amount=-1)
                    return self._retry_after_s(limiter, buckets)
        return None

    def _retry_after_s(self, limiter: FixedWindowRateLimiter, buckets: Sequence[Bucket]) -> float:
        now = self.clock()
        waits = [
            stats.reset_time - now
            for bucket in buckets
            for limit in self.limits
            if (stats := limiter.get_window_stats(limit, *bucket)).remaining == 0
        ]
        return max([1.0, *waits])

    def delay_s(self, session: Session, account: Bucket) -> float:
        """How long an attempt on `account` waits before its password is checked: 0 until `max_failures`
        failures from anywhere, then 1 s, doubling with each further failure, at most `delay_max_s`."""
        _limiter, storage = self._limiter(session)
        excess = storage.get(self.account_failures.key_for(*account)) - self.max_failures
        return 0.0 if excess < 0 else min(self.delay_max_s, 2.0 ** min(excess, 62))

    def failed(self, session: Session, account: Bucket) -> None:
        """A wrong password for `account` (the addresses keep the slots `reserve` took)."""
        _limiter, storage = self._limiter(session)
        storage.incr(self.account_failures.key_for(*account), self.account_failures.get_expiry())

    def succeeded(self, session: Session, *, account: Bucket, others: Sequence[Bucket]) -> None:
        """The password was right: the account's record is cleared, the other buckets get their slot back."""
        _limiter, storage = self._limiter(session)
        storage.clear(self.account_failures.key_for(*account))
        for limit in self.limits:
            storage.clear(limit.key_for(*account))  # records of before the delay: an upgrade leaves them
            for bucket in others:
                storage.incr(limit.key_for(*bucket), limit.get_expiry(), amount=-1)

    def unlock(self, session: Session, bucket: Bucket) -> None:
        """An admin lifts an address's back-off or an account's delay, whatever limits counted them (the
        keys name the limit: `login/address/10.0.0.5/5/300/second`)."""
        _limiter, storage = self._limiter(session)
        for namespace in {limit.namespace for limit in [*self.limits, self.account_failures]}:
            storage.clear_prefix("/".join([namespace, *bucket, ""]))
