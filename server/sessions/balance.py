"""`GET /patients/{id}/balance`: the balance-metric trend of a patient's recorded runs, for the profile page.

Per run: the Prieto (1996) sway measures (`core.posturography.sway_metrics`) of the net centre of pressure
of both feet (`net_cop`, plate COPs shifted to the stance frame by the foot-plate offsets), over the samples
where the patient loads the plates, and the number of falls recorded.
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Query, Request
from sqlalchemy import select

from core.posturography import net_cop, sway_metrics
from core.robot import TwinRobot
from server.api_types import IdPath
from server.auth.dependencies import CurrentUser, current_user
from server.db import SessionDep
from server.errors import ConflictError
from server.patients.service import read_patient
from server.scheduling.models import ScheduledSession
from server.sessions.logs import telemetry_columns
from server.sessions.models import SessionEvent, SessionRun

router = APIRouter(tags=["patients"], dependencies=[Depends(current_user)])

MIN_LOADED_SAMPLES = 3


def foot_origins_m(twin: TwinRobot) -> np.ndarray:
    """Each foot plate's (x, y) in the stance frame (right, left): plate COPs are measured from there."""
    offsets = np.array([twin.placement(side).foot_plate_offset_m[:2] for side in twin.sides], dtype=float)
    bases = np.array([twin.placement(side).base_origin_m[:2] for side in twin.sides], dtype=float)
    feet = bases + offsets
    return feet - feet.mean(axis=0)


def run_balance(columns: dict[str, np.ndarray], twin: TwinRobot) -> dict[str, float] | None:
    """Sway metrics of one run, or None when the plates were loaded for fewer than 3 samples."""
    forces = np.asarray(columns["plate_force_z_n"], dtype=float)
    loaded = forces.sum(axis=1) > 0.0
    if np.count_nonzero(loaded) < MIN_LOADED_SAMPLES:
        return None
    cop = net_cop(forces[loaded], np.asarray(columns["plate_cop_m"])[loaded], foot_origins_m(twin))
    return sway_metrics(np.asarray(columns["time_s"])[loaded], cop).to_dict()


@router.get("/patients/{patient_id}/balance")
def balance_trend(
    patient_id: IdPath,
    request: Request,
    session: SessionDep,
    user: CurrentUser,
    limit: Annotated[int, Query(ge=1, le=100, description="Most recent runs.")] = 20,
) -> list[dict[str, Any]]:
    """Oldest first: run id, start, outcome, falls and the sway measures (m, s; null when not recorded)."""
    read_patient(session=session, patient_id=patient_id, actor_id=user.id)
    runs = session.scalars(
        select(SessionRun)
        .join(ScheduledSession, ScheduledSession.id == SessionRun.scheduled_session_id)
        .where(ScheduledSession.patient_id == patient_id)
        .order_by(SessionRun.started_at.desc())
        .limit(limit)
    ).all()
    trend = []
    for run in reversed(runs):
        falls = session.scalars(
            select(SessionEvent.id).where(SessionEvent.run_id == run.id, SessionEvent.kind == "fall")
        ).all()
        try:
            metrics = run_balance(telemetry_columns(session=session, run_id=run.id), request.app.state.twin)
        except ConflictError:
            metrics = None  # no telemetry recorded for this run
        trend.append(
            {
                "run_id": run.id,
                "session_id": run.scheduled_session_id,
                "started_at": run.started_at,
                "outcome": run.outcome,
                "falls": len(falls),
                "sway": metrics,
            }
        )
    return trend
