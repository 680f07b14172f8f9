"""The robot daemon's plans ahead (issue 21, build 1): each booking's plan is built in the background, with
progress, as soon as it can be known (a booking made or moved, a prescription saved, at the latest when
the session page opens), stored once (`plan_store`), and Start plays the stored plan.

A plan's state, as the booking, the schedule and the session page show it:
- `planning`: queued or being built (`progress` 0–1);
- `ready`: stored and checked; Start plays it;
- `refused`: the check refused it (`reason` names the segment, the time, the limit and the value);
- `stale`: the booking's plan no longer matches (a new robot file, settings or patient mass); it is being
  made again and is never played.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from core.plan.build import PrescriptionPlan
from core.plan.prescription import PrescriptionError
from core.plan.rejection import PrescriptionRejected
from core.robot import TwinRobot, twin_digest
from server.db import Database
from server.errors import ConflictError, WorkerUnavailableError
from server.robotd import runs
from server.robotd.plan_store import PlanStore, plan_key
from server.robotd.planner import InlinePlanner, Planner, PlanningCancelled

log = logging.getLogger("ssp_rehab.robotd")


@dataclass
class PlanJob:
    key: str
    content: dict[str, Any]
    patient: dict[str, Any]
    progress: float = 0.0
    done: threading.Event | None = None
    failure: str | None = None  # the planner itself failed (not a refusal): said to the start waiting for it

    def __post_init__(self) -> None:
        self.done = threading.Event()


class PlanPreparer:
    def __init__(
        self,
        *,
        store: PlanStore,
        planner: Planner | InlinePlanner,
        twin: TwinRobot,
        database: Database,
        robot: str,
    ) -> None:
        self.store, self.planner, self.database, self.robot = store, planner, database, robot
        self.robot_digest = twin_digest(twin)
        self._lock = threading.Lock()
        self._jobs: dict[str, PlanJob] = {}  # queued or being built
        self._queue: queue.Queue[PlanJob | None] = queue.Queue()
        self._building: PlanJob | None = None
        self._last_key: dict[int, str] = {}  # booking → the key it was last shown with (for `stale`)
        self._thread = threading.Thread(target=self._build_forever, name="robotd-plans", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def shutdown(self) -> None:
        self._queue.put(None)

    # --- keys and state ---------------------------------------------------------------------------

    def key(self, content: dict[str, Any], patient: dict[str, Any]) -> str:
        return plan_key(
            content,
            patient,
            robot_digest=self.robot_digest,
            config=self.planner.supervisor.to_dict(),
            control_rate_hz=self.planner.control_rate_hz,
        )

    def _inputs(self, session_id: int) -> tuple[dict[str, Any], dict[str, Any]] | None:
        """The booking's prescription content and patient, or None when it is not this robot's to plan."""
        with self.database.session() as session:
            booking, version, patient = runs.plan_inputs(session=session, session_id=session_id)
            if booking.robot != self.robot or booking.status == "cancelled":
                return None
            return dict(version.content), runs.patient_for_worker(patient)

    def status(self, session_id: int) -> dict[str, Any] | None:
        """The booking's plan state (`planning`, `ready`, `refused`, `stale`); queues the plan when it is
        neither stored nor being built. None when the booking is not on this robot."""
        inputs = self._inputs(session_id)
        if inputs is None:
            return None
        key = self.key(*inputs)
        previous = self._last_key.get(session_id)
        self._last_key[session_id] = key
        if self.store.has(key):
            return {"state": "ready", "progress": 1.0, "reason": None, "plan_id": key}
        refusal = self.store.refusal(key)
        if refusal is not None:
            return {"state": "refused", "progress": 1.0, "reason": refusal["message"], "plan_id": key}
        job = self._queue_job(key, *inputs)
        state = "stale" if previous is not None and previous != key else "planning"
        return {"state": state, "progress": round(job.progress, 3), "reason": None, "plan_id": None}

    def _queue_job(self, key: str, content: dict[str, Any], patient: dict[str, Any]) -> PlanJob:
        with self._lock:
            job = self._jobs.get(key)
            if job is None:
                job = self._jobs[key] = PlanJob(key, content, patient)
                self._queue.put(job)
                log.info("plan %s queued", key)
            return job

    # --- Start --------------------------------------------------------------------------------------

    def obtain(
        self,
        content: dict[str, Any],
        patient: dict[str, Any],
        check: Callable[[], None],
        progress: Callable[[float], None] | None = None,
    ) -> tuple[PrescriptionPlan, dict[str, Any]]:
        """The checked plan for a start: the stored one, else the one being built (waited for), else built
        now; raises its refusal. `check` runs every 0.1 s meanwhile and raises when the start is cancelled."""
        key = self.key(content, patient)
        if not self.store.has(key) and self.store.refusal(key) is None:
            job = self._queue_job(key, content, patient)
            with self._lock:
                building = self._building
            if building is not None and building.key != key:
                self.planner.cancel()  # the patient is waiting: this plan first, the other one after
            self._prioritise(job)
            assert job.done is not None
            while not job.done.wait(0.1):
                check()
                if progress is not None:
                    progress(job.progress)
            if job.failure is not None:
                raise WorkerUnavailableError(f"the plan could not be built: {job.failure}")
        refusal = self.store.refusal(key)
        if refusal is not None:
            raise _refusal(refusal)
        return self.store.load(key)

    def _prioritise(self, job: PlanJob) -> None:
        """Put `job` at the head of the queue (it may be in it already: a job is built once, then skipped)."""
        with self._queue.mutex:
            self._queue.queue.appendleft(job)
            self._queue.not_empty.notify()

    # --- the builder --------------------------------------------------------------------------------

    def _build_forever(self) -> None:
        while True:
            job = self._queue.get()
            if job is None:
                return
            assert job.done is not None
            if job.done.is_set() or self.store.has(job.key) or self.store.refusal(job.key) is not None:
                job.done.set()
                continue
            with self._lock:
                self._building = job
            try:
                self._build(job)
            except PlanningCancelled:
                log.info("plan %s set aside for a start; queued again", job.key)
                self._queue.put(job)
                continue
            except Exception as error:  # the planner itself failed: said to a waiting start, tried again later
                log.exception("plan %s could not be built", job.key)
                job.failure = f"{type(error).__name__}: {error}"
            finally:
                with self._lock:
                    self._building = None
            with self._lock:
                self._jobs.pop(job.key, None)
            job.done.set()

    def _build(self, job: PlanJob) -> None:
        def progress(fraction: float) -> None:
            job.progress = fraction

        try:
            plan, report = self.planner.plan(job.content, job.patient, progress)
        except PrescriptionRejected as rejected:
            self.store.save_refusal(job.key, {"type": "rejected", **rejected.to_dict()})
            return
        except PrescriptionError as error:
            refusal = {"type": "invalid", "field": error.field, "value": repr(error.value), "limit": error.limit}
            self.store.save_refusal(job.key, {**refusal, "message": str(error)})
            return
        self.store.save(job.key, plan, report)
        log.info("plan %s ready (%d samples)", job.key, plan.played.samples)


def _refusal(stored: dict[str, Any]) -> Exception:
    if stored.get("type") == "rejected":
        return PrescriptionRejected.from_dict(stored)
    if stored.get("type") == "invalid":
        return PrescriptionError(stored["field"], stored["value"], stored["limit"])
    return ConflictError(str(stored.get("message")))
