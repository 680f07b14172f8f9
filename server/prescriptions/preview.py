"""Prescription previews: what a prescription would do, before it is stored or run.

`POST /prescriptions/previews` starts a preview job and answers at once (202, its id and a Location);
`GET /prescriptions/previews/{preview_id}` tells how it goes: `planning` with the fraction done, then `ready`
with the preview, or `refused` with the refusal in the items of a 422's `detail` (so the editor shows it at
its field), or `failed` if the preview process broke. The job's state is a file under the data directory
(`server.prescriptions.preview_jobs`): any web process of the console can answer the poll.

The preview builds the plan with the worker's own pipeline (`core.plan.build.build_plan`: cue × soft-start/fade
gains → washout (paper §4.1) and command shaping, or optimal cueing → quintic return to neutral → twin IK →
the independent check), then reports, decimated for plotting:
- the platform motion (stance pose, m and rad);
- the algorithm (`cueing`: classical washout or optimal cueing, issue 14);
- the specific force the patient should feel (the cue) and the one the platform gives at the patient's
  head (`core.perception.head_specific_force`, lever arm included), each through the otolith model
  (Formula 14), and the cued and delivered angular velocity through the canal model (Formula 15);
- every slider's position against its stroke;
and the check's verdict: the peak use of every limit, or the first limit it would break.

The work runs in a niced planning process of its own (`PreviewProcess`), never in the web process nor
inside a request: a preview holds the GIL for seconds in compiled kernels, and it starved the web process's
beat to its robot daemon, which ended a running session `interrupted` (issue 20, defect 8); a request that
waited for it held a request thread and showed no progress (issue 21, defect 6).
"""

from __future__ import annotations

import concurrent.futures
import functools
import logging
import multiprocessing
import threading
import time
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Path, Request, Response, status
from pydantic import ConfigDict, Field

from core.kinematics import twin_inverse_kinematics
from core.perception import head_angular_velocity, head_height_m, head_specific_force
from core.plan.build import Progress, build_plan
from core.plan.config import PlanConfig
from core.plan.prescription import PrescriptionBody, PrescriptionError
from core.plan.timeline import prescription_timeline
from core.robot import TwinRobot
from core.vestibular import VestibularModel
from server.api_types import MAX_ID, RequestModel
from server.auth.access import require_patient
from server.auth.dependencies import CurrentUser, current_user
from server.db import SessionDep
from server.errors import InvalidFieldError, NotFoundError
from server.jsonable import to_jsonable
from server.patients.service import read_patient
from server.prescriptions.preview_jobs import PreviewJobStore
from server.prescriptions.schemas import EXAMPLE_SEGMENT
from server.realtime.scheduling import lower_priority
from server.security import invalid_field_detail

logger = logging.getLogger(__name__)

router = APIRouter(prefix="/prescriptions", tags=["prescriptions"], dependencies=[Depends(current_user)])

PREVIEW_DURATION_MAX_S = 600.0  # bounds the work (and memory) of one preview at the control rate
PREVIEW_POINTS = 1200  # per curve: enough for a plot a screen wide
# Progress: the plan and its check are this far along (all but a second of an optimal plan's minutes; about
# two thirds of a classical one's second); the plots' curves take the rest, reported step by step.
PLANNING_SHARE = 0.7
PROGRESS_WRITE_S = 0.1  # the job's file is rewritten at most this often while it plans
PREVIEW_ID_PATTERN = r"^[0-9a-f]{32}$"


class PreviewRequest(PrescriptionBody, RequestModel):
    patient_id: Annotated[int | None, Field(ge=1, le=MAX_ID, description="Payload for the dynamics check.")] = None

    model_config = ConfigDict(json_schema_extra={"examples": [{"segments": [EXAMPLE_SEGMENT]}]})


def perceived_at_head(timeline: dict[str, np.ndarray], sample_period_s: float, head_height_m: float) -> dict:
    """The cue and what the platform delivers at the head, each through the vestibular models (N, 3)."""
    poses, velocity, acceleration = timeline["poses"], timeline["velocity"], timeline["acceleration"]
    delivered_force = head_specific_force(poses.T, velocity.T, acceleration.T, head_height_m).T
    delivered_rate = head_angular_velocity(poses.T, velocity.T).T
    model = VestibularModel(sample_period_s=sample_period_s)
    return {
        "delivered_specific_force_m_s2": delivered_force,
        "perceived_cue_m_s2": model.perceive_specific_force(timeline["force"]),
        "perceived_platform_m_s2": model.perceive_specific_force(delivered_force),
        "perceived_cue_rate_rad_s": model.perceive_angular_velocity(timeline["angular"]),
        "perceived_platform_rate_rad_s": model.perceive_angular_velocity(delivered_rate),
        "platform_rate_rad_s": delivered_rate,
    }


def check_preview_duration(prescription: PrescriptionBody) -> None:
    """Refuses a prescription longer than a preview covers, before any work."""
    total_s = sum(s.duration_s + PlanConfig().fade_out_s for s in prescription.segments)
    if total_s > PREVIEW_DURATION_MAX_S:
        raise InvalidFieldError(
            "segments", f"{total_s:g} s in all", f"the preview covers at most {PREVIEW_DURATION_MAX_S:g} s"
        )


def prescription_preview(
    prescription: PrescriptionBody,
    twin: TwinRobot,
    *,
    control_rate_hz: int,
    patient: dict[str, Any] | None = None,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """The preview of a validated prescription (SI units, time-major lists) and the worker's verdict.
    `progress` hears the fraction done (0 to 1, 1 only when the preview is complete)."""
    check_preview_duration(prescription)
    report = progress or (lambda _fraction: None)
    try:
        checked = build_plan(
            prescription,
            twin,
            control_rate_hz=control_rate_hz,
            patient=patient,
            progress=lambda fraction: report(PLANNING_SHARE * fraction),
        )
    except PrescriptionError as error:
        raise InvalidFieldError(error.field, error.value, error.limit) from error
    plan = checked.plan
    period = plan.sample_period_s
    timeline = prescription_timeline(plan)
    report(PLANNING_SHARE + (1.0 - PLANNING_SHARE) / 3)
    poses = timeline["poses"]
    head_m = head_height_m(plan.patient.height_m if plan.patient else None)
    perceived = perceived_at_head(timeline, period, head_m)
    report(PLANNING_SHARE + 2 * (1.0 - PLANNING_SHARE) / 3)
    rows = np.unique(np.linspace(0, len(poses) - 1, min(PREVIEW_POINTS, len(poses))).round().astype(int))
    # IK is per sample, so solving only the plotted rows gives the same positions for a fraction of the work.
    solutions = twin_inverse_kinematics(twin, poses[rows], check=False)
    sliders = np.full((len(poses), 12), np.nan)
    sliders[rows] = np.concatenate([solutions[side].slider_positions_m for side in twin.sides], axis=1)
    robots = [twin.robot_for(side) for side in twin.sides]
    verdict: dict[str, Any] = (
        {"accepted": False, "rejection": checked.rejection.to_dict()}
        if checked.rejection is not None
        else {"accepted": True, "report": checked.accepted().to_dict()}
    )

    def series(values: np.ndarray) -> list[Any]:
        picked = values[rows]
        # JSON has no NaN: an unreachable pose (no IK solution) is sent as null, and shown as a gap.
        return [None if not np.isfinite(v) else round(float(v), 6) for v in picked] if picked.ndim == 1 else [
            [None if not np.isfinite(v) else round(float(v), 6) for v in column] for column in picked.T
        ]  # fmt: skip

    preview = {
        "sample_rate_hz": control_rate_hz,
        "duration_s": round(len(poses) * period, 6),
        "time_s": series(np.arange(len(poses)) * period),
        "segment": timeline["segment"][rows].tolist(),
        "platform_position_m": series(poses[:, :3]),
        "platform_angles_rad": series(poses[:, 3:]),
        "cueing": plan.segments[0].cueing,
        "head_height_m": head_m,
        "cue_specific_force_m_s2": series(timeline["force"]),
        # What the platform delivers at the patient's head (lever arm included), and both through the otoliths.
        "platform_specific_force_m_s2": series(perceived["delivered_specific_force_m_s2"]),
        "perceived_cue_m_s2": series(perceived["perceived_cue_m_s2"]),
        "perceived_platform_m_s2": series(perceived["perceived_platform_m_s2"]),
        "cue_angular_velocity_rad_s": series(timeline["angular"]),
        "perceived_cue_rate_rad_s": series(perceived["perceived_cue_rate_rad_s"]),
        "perceived_platform_rate_rad_s": series(perceived["perceived_platform_rate_rad_s"]),
        "slider_position_m": series(sliders),
        "stroke_min_m": np.concatenate([r.stroke_min_m for r in robots]).tolist(),
        "stroke_max_m": np.concatenate([r.stroke_max_m for r in robots]).tolist(),
        "verdict": verdict,
    }
    report(1.0)
    return preview


class _ProgressFile:
    """The preview's progress callback in the preview process: the job's file, at most every
    `PROGRESS_WRITE_S` (the end is written with the preview)."""

    def __init__(self, jobs: PreviewJobStore, job: dict[str, Any]) -> None:
        self.jobs, self.job = jobs, job
        self.written_monotonic = time.monotonic()

    def __call__(self, fraction: float) -> None:
        progress = round(min(max(fraction, 0.0), 1.0), 4)
        now = time.monotonic()
        if self.job["progress"] < progress < 1.0 and now - self.written_monotonic >= PROGRESS_WRITE_S:
            self.job = {**self.job, "progress": progress}
            self.jobs.write(self.job)
            self.written_monotonic = now


def run_preview_job(
    jobs: PreviewJobStore,
    job: dict[str, Any],
    prescription: PrescriptionBody,
    twin: TwinRobot,
    control_rate_hz: int,
    patient: dict[str, Any] | None,
) -> None:
    """In the preview process: computes the job's preview, writing its progress, then `ready` with the preview
    or `refused` with the refusal as the items of a 422's `detail`."""
    report = _ProgressFile(jobs, job)
    try:
        preview = prescription_preview(
            prescription, twin, control_rate_hz=control_rate_hz, patient=patient, progress=report
        )
    except InvalidFieldError as error:
        jobs.write({**report.job, "state": "refused", "progress": 1.0, "refusal": invalid_field_detail(error)})
        return
    jobs.write({**report.job, "state": "ready", "progress": 1.0, "preview": to_jsonable(preview)})


class PreviewProcess:
    """One niced process per web process that computes preview jobs one at a time (started on first use)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None

    def _executor(self) -> concurrent.futures.ProcessPoolExecutor:
        with self._lock:
            if self._pool is None:
                self._pool = concurrent.futures.ProcessPoolExecutor(
                    max_workers=1,
                    mp_context=multiprocessing.get_context("spawn"),
                    initializer=lower_priority,
                    initargs=("the preview process",),
                )
            return self._pool

    def _forget(self, pool: concurrent.futures.ProcessPoolExecutor) -> None:
        with self._lock:
            if self._pool is pool:
                self._pool = None  # the next preview starts a new process

    def submit(
        self,
        jobs: PreviewJobStore,
        job: dict[str, Any],
        prescription: PrescriptionBody,
        twin: TwinRobot,
        *,
        control_rate_hz: int,
        patient: dict[str, Any] | None,
    ) -> None:
        """Queues the job; it ends `failed` if the preview process breaks or the console stops first."""
        pool = self._executor()
        try:
            future = pool.submit(run_preview_job, jobs, job, prescription, twin, control_rate_hz, patient)
        except concurrent.futures.process.BrokenProcessPool:
            self._forget(pool)
            jobs.write({**job, "state": "failed", "error": "the preview process stopped: ask again"})
            raise
        future.add_done_callback(functools.partial(self._finished, jobs, job, pool))

    def _finished(
        self,
        jobs: PreviewJobStore,
        job: dict[str, Any],
        pool: concurrent.futures.ProcessPoolExecutor,
        future: concurrent.futures.Future[None],
    ) -> None:
        if future.cancelled():
            error = "the console stopped before the preview was computed: ask again"
        else:
            failure = future.exception()
            if failure is None:
                return  # the preview process wrote the job's end
            if isinstance(failure, concurrent.futures.process.BrokenProcessPool):
                self._forget(pool)
            logger.error("preview %s failed", job["preview_id"], exc_info=failure)
            error = f"the preview could not be computed ({type(failure).__name__}); the console's log says why"
        try:
            jobs.write({**job, "state": "failed", "error": error})
        except OSError:
            logger.exception("preview %s: its failure could not be recorded", job["preview_id"])

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)


@router.post(
    "/previews",
    status_code=status.HTTP_202_ACCEPTED,
    responses={422: {"description": "A field is invalid; the answer names it (no job is started)"}},
)
def start_preview(
    data: PreviewRequest, request: Request, response: Response, session: SessionDep, user: CurrentUser
) -> dict[str, Any]:
    """Starts the preview of the segments as the robot would play them: follow it at the Location given."""
    patient = None
    if data.patient_id is not None:
        require_patient(session, user, data.patient_id)
        record = read_patient(session=session, patient_id=data.patient_id, actor_id=user.id)
        patient = {"body_mass_kg": record.body_mass_kg, "height_m": record.height_m}
    check_preview_duration(data)
    jobs = preview_jobs(request)
    job = jobs.create(user.id)
    settings = request.app.state.settings
    twin = request.app.state.twin
    preview_process(request).submit(jobs, job, data, twin, control_rate_hz=settings.control_rate_hz, patient=patient)
    response.headers["Location"] = request.app.url_path_for("preview_job", preview_id=job["preview_id"])
    return {"preview_id": job["preview_id"], "state": job["state"], "progress": job["progress"]}


@router.get("/previews/{preview_id}", name="preview_job")
def preview_job(
    preview_id: Annotated[str, Path(pattern=PREVIEW_ID_PATTERN)], request: Request, user: CurrentUser
) -> dict[str, Any]:
    """state (planning | ready | refused | failed), progress 0–1, and the preview, the refusal (the items of
    a 422's detail) or why it failed; for the user who asked for it only."""
    job = preview_jobs(request).read(preview_id, user.id)
    if job is None:
        raise NotFoundError("preview", preview_id)
    return job


def preview_process(request: Request) -> PreviewProcess:
    """The app's preview process (`create_app` makes it; shut down with the app)."""
    process: PreviewProcess = request.app.state.preview_process
    return process


def preview_jobs(request: Request) -> PreviewJobStore:
    """The app's preview jobs (`create_app` makes the store, under the data directory)."""
    jobs: PreviewJobStore = request.app.state.preview_jobs
    return jobs
