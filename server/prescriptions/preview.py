"""`POST /prescriptions/preview`: what a prescription would do, before it is stored or run.

It builds the plan with the worker's own pipeline (`core.plan.build.build_plan`: cue × soft-start/fade gains
→ washout (paper §4.1) and command shaping, or optimal cueing → quintic return to neutral → twin IK → the
independent check), then reports, decimated for plotting:
- the platform motion (stance pose, m and rad);
- the algorithm (`cueing`: classical washout or optimal cueing, issue 14);
- the specific force the patient should feel (the cue) and the one the platform gives at the patient's
  head (`core.perception.head_specific_force`, lever arm included), each through the otolith model
  (Formula 14), and the cued and delivered angular velocity through the canal model (Formula 15);
- every slider's position against its stroke;
and the check's verdict: the peak use of every limit, or the first limit it would break.

The work runs in a niced planning process of its own (`PreviewProcess`), never in the web process: a
preview holds the GIL for seconds in compiled kernels, and it starved the web process's beat to its
robot daemon, which ended a running session `interrupted` (issue 20, defect 8).
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import threading
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Request
from pydantic import ConfigDict, Field

from core.kinematics import twin_inverse_kinematics
from core.perception import head_angular_velocity, head_height_m, head_specific_force
from core.plan.build import build_plan
from core.plan.config import PlanConfig
from core.plan.prescription import PrescriptionBody, PrescriptionError
from core.plan.timeline import prescription_timeline
from core.robot import TwinRobot
from core.vestibular import VestibularModel
from server.api_types import MAX_ID, RequestModel
from server.auth.access import require_patient
from server.auth.dependencies import CurrentUser, current_user
from server.db import SessionDep
from server.errors import InvalidFieldError
from server.patients.service import read_patient
from server.prescriptions.schemas import EXAMPLE_SEGMENT
from server.realtime.scheduling import lower_priority

router = APIRouter(prefix="/prescriptions", tags=["prescriptions"], dependencies=[Depends(current_user)])

PREVIEW_DURATION_MAX_S = 600.0  # bounds the work (and memory) of one preview at the control rate
PREVIEW_POINTS = 1200  # per curve: enough for a plot a screen wide


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


def prescription_preview(
    prescription: PrescriptionBody, twin: TwinRobot, *, control_rate_hz: int, patient: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The preview of a validated prescription (SI units, time-major lists) and the worker's verdict."""
    total_s = sum(s.duration_s + PlanConfig().fade_out_s for s in prescription.segments)
    if total_s > PREVIEW_DURATION_MAX_S:  # refused before any work
        raise InvalidFieldError(
            "segments", f"{total_s:g} s in all", f"the preview covers at most {PREVIEW_DURATION_MAX_S:g} s"
        )
    try:
        checked = build_plan(prescription, twin, control_rate_hz=control_rate_hz, patient=patient)
    except PrescriptionError as error:
        raise InvalidFieldError(error.field, error.value, error.limit) from error
    plan = checked.plan
    period = plan.sample_period_s
    timeline = prescription_timeline(plan)
    poses = timeline["poses"]
    head_m = head_height_m(plan.patient.height_m if plan.patient else None)
    perceived = perceived_at_head(timeline, period, head_m)
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

    return {
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


def _preview_or_refusal(
    prescription: PrescriptionBody, twin: TwinRobot, control_rate_hz: int, patient: dict[str, Any] | None
) -> tuple[str, Any]:
    """In the preview process: ("ok", preview) or ("invalid", (field, value, limit)), which pickles back."""
    try:
        return "ok", prescription_preview(prescription, twin, control_rate_hz=control_rate_hz, patient=patient)
    except InvalidFieldError as error:
        return "invalid", (error.field, error.value, error.limit)


class PreviewProcess:
    """One niced process per web process that computes previews one at a time (started on first use)."""

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

    def preview(
        self, prescription: PrescriptionBody, twin: TwinRobot, *, control_rate_hz: int, patient: dict[str, Any] | None
    ) -> dict[str, Any]:
        try:
            future = self._executor().submit(_preview_or_refusal, prescription, twin, control_rate_hz, patient)
            status, result = future.result()
        except concurrent.futures.process.BrokenProcessPool:
            with self._lock:
                self._pool = None  # the next preview starts a new process
            raise
        if status == "invalid":
            raise InvalidFieldError(*result)
        return dict(result)

    def close(self) -> None:
        with self._lock:
            pool, self._pool = self._pool, None
        if pool is not None:
            pool.shutdown(wait=False, cancel_futures=True)


@router.post("/preview", responses={422: {"description": "A field is invalid; the answer names it"}})
def preview_prescription(
    data: PreviewRequest, request: Request, session: SessionDep, user: CurrentUser
) -> dict[str, Any]:
    """Plots-ready preview of the segments as the robot would play them, and whether the robot accepts them."""
    patient = None
    if data.patient_id is not None:
        require_patient(session, user, data.patient_id)
        record = read_patient(session=session, patient_id=data.patient_id, actor_id=user.id)
        patient = {"body_mass_kg": record.body_mass_kg, "height_m": record.height_m}
    return preview_process(request).preview(
        data,
        request.app.state.twin,
        control_rate_hz=request.app.state.settings.control_rate_hz,
        patient=patient,
    )


def preview_process(request: Request) -> PreviewProcess:
    """The app's preview process (`create_app` makes it; shut down with the app)."""
    process: PreviewProcess = request.app.state.preview_process
    return process
