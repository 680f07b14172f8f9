"""The daemon's planning process: prescriptions are planned and checked offline here, never in a web
request, an event loop or the real-time worker, so an emergency stop or a health check never waits
for a long check (issue 12, defect 1)."""

from __future__ import annotations

import logging
import multiprocessing
import threading
from multiprocessing.connection import Connection
from typing import Any

from core.plan.build import PrescriptionPlan, build_plan
from core.plan.check import PrescriptionRejected
from core.plan.prescription import PrescriptionError
from core.robot import default_twin, load_twin
from server.realtime.scheduling import lower_priority
from server.realtime.supervisor import SupervisorConfig

log = logging.getLogger("ssp_rehab.robotd")


def _planner_entry(twin_path: str | None, control_rate_hz: int, supervisor: dict[str, Any], link: Connection) -> None:
    """Process entry point: answer (prescription, patient) with ("ok", plan, report) or the refusal."""
    lower_priority("the planning process")  # planning yields to the worker, the recorder and the beats
    twin = load_twin(twin_path) if twin_path else default_twin()
    config = SupervisorConfig.from_dict(supervisor)
    while True:
        try:
            prescription, patient = link.recv()
        except EOFError:
            return
        try:
            checked = build_plan(prescription, twin, control_rate_hz=control_rate_hz, config=config, patient=patient)
            link.send(("ok", checked.plan, checked.accepted().to_dict()))
        except PrescriptionRejected as rejected:
            link.send(("rejected", rejected.to_dict(), None))
        except PrescriptionError as error:
            link.send(("invalid", {"field": error.field, "value": repr(error.value), "limit": error.limit}, None))
        except Exception as error:  # a bad prescription must not take the planner down
            link.send(("error", f"{type(error).__name__}: {error}", None))


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
        self, prescription: dict[str, Any], patient: dict[str, Any] | None
    ) -> tuple[PrescriptionPlan, dict[str, Any]]:
        """The checked plan and its report; raises the refusal (PrescriptionRejected / PrescriptionError)."""
        with self._lock:
            if self._process is None or not self._process.is_alive():
                self.start()
            assert self._link is not None
            self._cancelled = False
            self.busy.set()
            try:
                self._link.send((prescription, patient))
                status, result, report = self._link.recv()
            except (EOFError, OSError) as error:
                dead, self._process = self._process, None
                if dead is not None:
                    dead.join(5.0)
                if self._cancelled:
                    raise PlanningCancelled("the check was abandoned: the start was cancelled") from error
                raise RuntimeError(f"the planning process died while checking the prescription ({error})") from error
            finally:
                self.busy.clear()
        if status == "ok":
            return result, report
        if status == "rejected":
            raise PrescriptionRejected(
                result["segment"], result["time_s"], result["limit"], result["value"], result["message"]
            )
        if status == "invalid":
            raise PrescriptionError(result["field"], result["value"], result["limit"])
        raise RuntimeError(result)

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
