"""The daemon's planning process: prescriptions are planned and checked offline here, never in a web
request, an event loop or the real-time worker, so an emergency stop or a health check never waits
for a long check (issue 12, defect 1)."""

from __future__ import annotations

import logging
import multiprocessing
import threading
from multiprocessing.connection import Connection
from typing import Any

from core.plan.build import PrescriptionPlan, Progress, build_plan
from core.robot import TwinRobot, default_twin, load_twin
from server.messages import PlanProgress, PlanReady, PlanRequest, Refusal, refusal_of
from server.realtime.scheduling import lower_priority
from server.realtime.supervisor import SupervisorConfig

log = logging.getLogger("ssp_rehab.robotd")
PROGRESS_STEP = 0.01  # the planning process reports its progress in steps of this fraction


def checked_plan(
    twin: TwinRobot,
    control_rate_hz: int,
    config: SupervisorConfig,
    prescription: dict[str, Any],
    patient: dict[str, Any] | None,
    progress: Progress | None = None,
) -> tuple[PrescriptionPlan, dict[str, Any]]:
    """The plan and its check report; raises the refusal (`PrescriptionRejected` / `PrescriptionError`)."""
    checked = build_plan(
        prescription, twin, control_rate_hz=control_rate_hz, config=config, patient=patient, progress=progress
    )
    return checked.plan, checked.accepted().to_dict()


def _planner_entry(twin_path: str | None, control_rate_hz: int, supervisor: dict[str, Any], link: Connection) -> None:
    """Process entry point: answer each `PlanRequest` with `PlanProgress` messages, then `PlanReady` or the
    `Refusal`."""
    lower_priority("the planning process")  # planning yields to the worker, the recorder and the beats
    twin = load_twin(twin_path) if twin_path else default_twin()
    config = SupervisorConfig.from_dict(supervisor)
    while True:
        try:
            request: PlanRequest = link.recv()
        except EOFError:
            return

        def progress(fraction: float, reported: list[float] = [0.0]) -> None:  # noqa: B006 — one per plan
            if fraction - reported[0] >= PROGRESS_STEP:
                reported[0] = fraction
                link.send(PlanProgress(fraction))

        try:
            plan, report = checked_plan(twin, control_rate_hz, config, request.prescription, request.patient, progress)
            link.send(PlanReady(plan, report))
        except Exception as error:  # a refusal, or a bad prescription: it must not take the planner down
            link.send(refusal_of(error))


class PlanningCancelled(RuntimeError):  # noqa: N818 — a decision, not a malfunction
    """The check was abandoned on purpose."""


class Planner:
    """The daemon's handle on its planning process (restarted if it dies)."""

    def __init__(self, twin_path: str | None, control_rate_hz: int, supervisor: SupervisorConfig) -> None:
        self.twin_path, self.control_rate_hz, self.supervisor = twin_path, control_rate_hz, supervisor
        self._lock = threading.Lock()
        self._process: multiprocessing.process.BaseProcess | None = None
        self._link: Connection | None = None
        self.busy = threading.Event()  # set while a prescription is being checked
        self._cancelled = False

    def start(self) -> None:
        context = multiprocessing.get_context("spawn")
        self._link, child = context.Pipe()
        self._process = context.Process(
            target=_planner_entry,
            args=(self.twin_path, self.control_rate_hz, self.supervisor.to_dict(), child),
            name="ssp-rehab-planner",
            daemon=True,
        )
        self._process.start()
        child.close()

    @property
    def pid(self) -> int | None:
        return self._process.pid if self._process is not None else None

    def plan(
        self, prescription: dict[str, Any], patient: dict[str, Any] | None, progress: Progress | None = None
    ) -> tuple[PrescriptionPlan, dict[str, Any]]:
        """The checked plan and its report; raises the refusal (PrescriptionRejected / PrescriptionError).
        `progress` hears the fraction done as the planning process reports it."""
        with self._lock:
            if self._process is None or not self._process.is_alive():
                self.start()
            assert self._link is not None
            self._cancelled = False
            self.busy.set()
            try:
                self._link.send(PlanRequest(prescription=prescription, patient=patient))
                answer = self._link.recv()
                while isinstance(answer, PlanProgress):
                    if progress is not None:
                        progress(answer.fraction)
                    answer = self._link.recv()
            except (EOFError, OSError) as error:
                dead, self._process = self._process, None
                if dead is not None:
                    dead.join(5.0)
                if self._cancelled:
                    raise PlanningCancelled("the check was abandoned: the start was cancelled") from error
                raise RuntimeError(f"the planning process died while checking the prescription ({error})") from error
            finally:
                self.busy.clear()
        if isinstance(answer, Refusal):
            raise answer.error()
        ready: PlanReady = answer
        return ready.plan, ready.report

    def cancel(self) -> None:
        """Abandon the check under way (a start cancelled by a stop): its process is ended, and the waiting
        `plan` raises `PlanningCancelled`; the next plan starts a fresh process."""
        process = self._process
        if self.busy.is_set() and process is not None and process.is_alive():
            self._cancelled = True
            process.kill()

    def shutdown(self) -> None:
        if self._link is not None:
            self._link.close()
        if self._process is not None:
            self._process.join(5.0)
            if self._process.is_alive():
                self._process.terminate()
        self._process = None


class InlinePlanner:
    """The same planning in the caller's thread: for a daemon in the web process's tests, whose worker is
    an in-memory fake. The worker's side (`load_plan`, the checked transitions) is the production one."""

    def __init__(self, twin: TwinRobot, control_rate_hz: int, supervisor: SupervisorConfig) -> None:
        self.twin, self.control_rate_hz, self.supervisor = twin, control_rate_hz, supervisor
        self.busy = threading.Event()
        self.planned = 0  # plans built so far

    def plan(
        self, prescription: dict[str, Any], patient: dict[str, Any] | None, progress: Progress | None = None
    ) -> tuple[PrescriptionPlan, dict[str, Any]]:
        self.busy.set()
        self.planned += 1
        try:
            return checked_plan(self.twin, self.control_rate_hz, self.supervisor, prescription, patient, progress)
        finally:
            self.busy.clear()

    def cancel(self) -> None:
        """Nothing to abandon: the caller is the planner (the start's own refusal follows)."""

    def shutdown(self) -> None:
        pass
