"""Prometheus metrics (prometheus-client): API latency by route, and the robot's tick timing, counters
and state, read from what the real-time worker already publishes.

The robot's metrics live in the robot daemon, the one reader of the worker's streams: `WorkerTap` wraps
the worker the daemon's recorder drains, forwards `drain_telemetry()`, `drain_events()` and
`latest_state()` unchanged and observes what passes into `RobotMetrics`. Every web process serves its own
`ServiceMetrics` followed by the daemon's robot metrics (asked over its socket), so several web
processes show one robot's figures once, and a web crash loses none of them.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

# Tick timing at 1 kHz: the interesting range is tens of µs up to several periods.
TICK_BUCKETS_S = (
    10e-6, 25e-6, 50e-6, 75e-6, 100e-6, 150e-6, 250e-6, 500e-6, 1e-3, 2e-3, 5e-3, 10e-3, 50e-3,
)  # fmt: skip
REQUEST_BUCKETS_S = (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
ROBOT_STATES = ("idle", "ready", "running", "paused", "stopping", "stopped", "estop", "fault")
EVENT_COUNTERS = {"emergency_stop": "emergency_stops", "fault": "faults"}


class ServiceMetrics:
    """One web process's metrics, in its own registry (one per app, so that tests stay apart)."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        registry = self.registry
        self.request_seconds = Histogram(
            "ssp_rehab_http_request_duration_seconds",
            "API request latency, by route template (no ids, no query strings).",
            ("method", "route", "status"),
            buckets=REQUEST_BUCKETS_S,
            registry=registry,
        )
        self.robot_connected = Gauge(
            "ssp_rehab_robot_connected", "1 while the robot daemon is attached and ready.", registry=registry
        )
        self.active_run = Gauge(
            "ssp_rehab_session_run_active", "1 while a session run is being recorded.", registry=registry
        )


class RobotMetrics:
    """The robot's metrics, kept by its daemon from everything the worker publishes."""

    def __init__(self) -> None:
        self.registry = CollectorRegistry()
        registry = self.registry
        self.tick_compute_seconds = Histogram(
            "ssp_rehab_robot_tick_compute_seconds",
            "Compute time of one real-time tick.",
            buckets=TICK_BUCKETS_S,
            registry=registry,
        )
        self.tick_lateness_seconds = Histogram(
            "ssp_rehab_robot_tick_lateness_seconds",
            "How late a real-time tick started after its deadline.",
            buckets=TICK_BUCKETS_S,
            registry=registry,
        )
        self.deadline_misses = Counter(
            "ssp_rehab_robot_deadline_misses", "Real-time ticks that missed their deadline.", registry=registry
        )
        self.limit_hits = Counter(
            "ssp_rehab_robot_limit_hits", "Safety-limit hits reported by the worker.", registry=registry
        )
        self.emergency_stops = Counter(
            "ssp_rehab_robot_emergency_stops", "Emergency stops latched by the worker.", registry=registry
        )
        self.faults = Counter("ssp_rehab_robot_faults", "Faults reported by the worker.", registry=registry)
        self.telemetry_lost = Counter(
            "ssp_rehab_robot_telemetry_lost",
            "Telemetry records lost before the robot daemon drained them.",
            registry=registry,
        )
        self.telemetry_records = Counter(
            "ssp_rehab_robot_telemetry_records", "Telemetry records drained from the worker.", registry=registry
        )
        self.robot_state = Gauge(
            "ssp_rehab_robot_state",
            "1 for the worker's current state, 0 for the others.",
            ("state",),
            registry=registry,
        )
        self.estop_latched = Gauge(
            "ssp_rehab_robot_estop_latched", "1 while an emergency stop is latched.", registry=registry
        )
        for state in ROBOT_STATES:
            self.robot_state.labels(state=state)


class WorkerTap:
    """The worker as the session recorder sees it, with every drained record and event observed on the
    way through. Other attributes pass straight to the worker."""

    def __init__(self, worker: Any, metrics: RobotMetrics) -> None:
        self._worker = worker
        self._metrics = metrics
        self._lock = threading.Lock()
        self._last_cumulative: dict[str, int] = {}
        self._last_lost: int | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._worker, name)

    def drain_telemetry(self) -> np.ndarray:
        records = self._worker.drain_telemetry()
        if records is not None and len(records):
            self._observe_telemetry(records)
        self._observe_lost()
        return records

    def drain_events(self) -> list[dict[str, Any]]:
        events: list[dict[str, Any]] = self._worker.drain_events()
        for event in events:
            counter = EVENT_COUNTERS.get(str(event.get("kind")))
            if counter is not None:
                getattr(self._metrics, counter).inc()
        return events

    def latest_state(self) -> dict[str, Any]:
        state: dict[str, Any] = self._worker.latest_state()
        current = str(state.get("state", ""))
        for name in ROBOT_STATES:
            self._metrics.robot_state.labels(state=name).set(1.0 if name == current else 0.0)
        self._metrics.estop_latched.set(1.0 if state.get("estop_latched") else 0.0)
        return state

    def _observe_telemetry(self, records: np.ndarray) -> None:
        names = records.dtype.names or ()
        metrics = self._metrics
        metrics.telemetry_records.inc(len(records))
        for field, histogram in (
            ("tick_compute_us", metrics.tick_compute_seconds),
            ("lateness_us", metrics.tick_lateness_seconds),
        ):
            if field in names:
                for value in (records[field].astype(np.float64) * 1e-6).tolist():
                    histogram.observe(value)
        for field, counter in (("deadline_misses", metrics.deadline_misses), ("limit_hits", metrics.limit_hits)):
            if field in names:
                self._count_cumulative(field, int(records[field][-1]), counter)

    def _count_cumulative(self, field: str, latest: int, counter: Counter) -> None:
        """The worker counts from its start; a smaller value means a new worker, counted from zero."""
        with self._lock:
            previous = self._last_cumulative.get(field, 0)
            self._last_cumulative[field] = latest
        counter.inc(latest - previous if latest >= previous else latest)

    def _observe_lost(self) -> None:
        lost = getattr(self._worker, "telemetry_lost", None)
        if not isinstance(lost, int):
            return
        with self._lock:
            previous, self._last_lost = self._last_lost, lost
        if previous is not None:
            self._metrics.telemetry_lost.inc(lost - previous if lost >= previous else lost)
        elif lost:
            self._metrics.telemetry_lost.inc(lost)
