"""A patient's balance over time, for the profile page (issue 16 §5).

`GET /patients/{id}/trends` returns every trend series of a patient in one request: per recorded run its date,
outcome (faulted runs and falls marked) and the Prieto et al. (1996) sway measures of the net centre of pressure
of both feet (`net_cop`: plate COPs shifted to the stance frame by the foot-plate offsets), computed on the COP
low-pass filtered at 5 Hz like Prieto did (`core.posturography.filtered_sway_metrics`). They are taken over
one stated window of each run: the longest stretch of the run in motion (running or paused, not the approach's
wait before the start or the recording's tail after the end) in which the patient loads the plates. The window
must last at least `MIN_WINDOW_S`, 20 s, the trial length of the clinical sensory organisation test: a run
stopped after a few seconds has no sway measures (issue 22 §6). Each series has one unit, so a chart can give
it its own axis.

No normative band is given: the published ranges we know of were measured on a fixed force plate in quiet
stance, not on moving platforms during training, and none could be checked offline. A band may only be added
with its source (`NORMATIVE_BANDS`).

`GET /patients/{id}/balance` is the older per-run list (now on the filtered COP too), kept for the console.
"""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Query, Request
from sqlalchemy import select

from core.posturography import (
    COP_LOWPASS_CUTOFF_HZ,
    COP_LOWPASS_ORDER,
    filtered_sway_metrics,
    net_cop,
)
from core.robot import TwinRobot
from server.api_types import IdPath
from server.auth.access import ObjectAccess
from server.auth.dependencies import CurrentUser, current_user
from server.db import SessionDep
from server.errors import ConflictError, InvalidFieldError
from server.patients.service import read_patient
from server.realtime.telemetry import SupervisorState
from server.robotd.models import SessionEvent, SessionRun
from server.scheduling.models import ScheduledSession
from server.sessions.logs import telemetry_columns

router = APIRouter(tags=["patients"], dependencies=[Depends(current_user), ObjectAccess])

MIN_LOADED_SAMPLES = 3
LOADED_PLATES_N = 50.0  # below this both plates together carry nobody: no COP to speak of
MIN_WINDOW_S = 20.0  # the shortest window measured: one trial of the clinical sensory organisation test
IN_MOTION = (SupervisorState.RUNNING, SupervisorState.PAUSED)
MAX_TREND_RUNS = 500

# Outcomes of a run (server/robotd/records.py) as the trend marks them.
GOOD_OUTCOMES = ("completed", "stopped")
# (key, label, unit, metric field, factor from SI); `falls` is counted from the run's events.
TREND_SERIES = (
    ("mean_velocity", "Mean COP velocity", "mm/s", "mean_velocity_m_s", 1e3),
    ("path_length", "COP path length", "mm", "path_length_m", 1e3),
    ("mean_distance", "Mean distance from the mean COP", "mm", "mean_distance_m", 1e3),
    ("rms_distance", "RMS distance from the mean COP", "mm", "rms_distance_m", 1e3),
    ("range_ap", "Anterior-posterior range", "mm", "range_ap_m", 1e3),
    ("range_ml", "Medio-lateral range", "mm", "range_ml_m", 1e3),
    ("ellipse_area_95", "95 % prediction ellipse area", "cm²", "ellipse_area_95_m2", 1e4),
)
# Published normative bands, per series key: {"low", "high", "unit", "population", "condition", "source"}.
# Empty on purpose: see the module docstring. Never add a band without its source.
NORMATIVE_BANDS: dict[str, dict[str, Any]] = {}


def foot_origins_m(twin: TwinRobot) -> np.ndarray:
    """Each foot plate's (x, y) in the stance frame (right, left): plate COPs are measured from there."""
    offsets = np.array([twin.placement(side).foot_plate_offset_m[:2] for side in twin.sides], dtype=float)
    bases = np.array([twin.placement(side).base_origin_m[:2] for side in twin.sides], dtype=float)
    feet = bases + offsets
    return feet - feet.mean(axis=0)


def longest_loaded_stretch(forces: np.ndarray, within: np.ndarray | None = None) -> slice:
    """The longest run of samples in which the plates together carry at least `LOADED_PLATES_N` (and, given
    `within`, a mask of the samples that may count, only those)."""
    usable = forces.sum(axis=1) >= LOADED_PLATES_N
    if within is not None:
        usable &= within
    loaded = np.concatenate([[0], usable.astype(np.int8), [0]])
    edges = np.diff(loaded)
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    if not len(starts):
        return slice(0, 0)
    longest = int(np.argmax(ends - starts))
    return slice(int(starts[longest]), int(ends[longest]))


def run_balance(columns: dict[str, np.ndarray], twin: TwinRobot) -> dict[str, float] | None:
    """Prieto's sway measures of one run on the filtered net COP (m, s) over its window (`window_from_s` and
    `window_to_s`, seconds into the run), or None when the run in motion loaded the plates for less than
    `MIN_WINDOW_S` in a row."""
    forces = np.asarray(columns["plate_force_z_n"], dtype=float)
    in_motion = np.isin(np.asarray(columns["state"]), [int(state) for state in IN_MOTION])
    stretch = longest_loaded_stretch(forces, within=in_motion)
    time_s = np.asarray(columns["time_s"], dtype=float)[stretch]
    if stretch.stop - stretch.start < MIN_LOADED_SAMPLES or time_s[-1] - time_s[0] < MIN_WINDOW_S:
        return None
    cop = net_cop(forces[stretch], np.asarray(columns["plate_cop_m"], dtype=float)[stretch], foot_origins_m(twin))
    into_run = np.asarray(columns["session_time_s"], dtype=float)[stretch]
    return {
        **filtered_sway_metrics(time_s, cop).to_dict(),
        "window_from_s": float(into_run[0]),
        "window_to_s": float(into_run[-1]),
    }


def run_status(outcome: str | None) -> str:
    """ok, fall, faulted (limit hit, fault, watchdog, emergency stop, ...) or in_progress."""
    if outcome is None:
        return "in_progress"
    if outcome in GOOD_OUTCOMES:
        return "ok"
    return "fall" if outcome == "fall" else "faulted"


def _runs_of(session: Any, patient_id: int, start: dt.date | None, end: dt.date | None, limit: int) -> list[Any]:
    query = (
        select(SessionRun)
        .join(ScheduledSession, ScheduledSession.id == SessionRun.scheduled_session_id)
        .where(ScheduledSession.patient_id == patient_id)
    )
    if start is not None:
        query = query.where(SessionRun.started_at >= dt.datetime.combine(start, dt.time(), dt.UTC))
    if end is not None:
        query = query.where(SessionRun.started_at < dt.datetime.combine(end + dt.timedelta(days=1), dt.time(), dt.UTC))
    return list(reversed(session.scalars(query.order_by(SessionRun.started_at.desc()).limit(limit)).all()))


def _run_entry(session: Any, run: Any, twin: TwinRobot) -> dict[str, Any]:
    falls = session.scalars(
        select(SessionEvent.id).where(SessionEvent.run_id == run.id, SessionEvent.kind == "fall")
    ).all()
    try:
        metrics = run_balance(telemetry_columns(session=session, run_id=run.id), twin)
    except ConflictError:
        metrics = None  # no telemetry recorded for this run
    started = run.started_at if run.started_at.tzinfo else run.started_at.replace(tzinfo=dt.UTC)
    return {
        "run_id": run.id,
        "session_id": run.scheduled_session_id,
        "started_at": started,
        "date": started.date().isoformat(),
        "outcome": run.outcome,
        "status": run_status(run.outcome),
        "falls": len(falls),
        "sway": metrics,
    }


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
    return [
        _run_entry(session, run, request.app.state.twin) for run in _runs_of(session, patient_id, None, None, limit)
    ]


@router.get("/patients/{patient_id}/trends")
def balance_trends(
    patient_id: IdPath,
    request: Request,
    session: SessionDep,
    user: CurrentUser,
    from_date: Annotated[dt.date | None, Query(description="First day (UTC) of runs to include.")] = None,
    to_date: Annotated[dt.date | None, Query(description="Last day (UTC) of runs to include.")] = None,
    limit: Annotated[int, Query(ge=1, le=MAX_TREND_RUNS, description="Most recent runs.")] = 200,
) -> dict[str, Any]:
    """Every balance trend of a patient by date, in one response.

    `runs`: oldest first, each with its date, outcome, `status` (ok, fall, faulted, in_progress), falls and the
    sway measures in SI (null without force-plate data). `series`: one per measure, with its label and its one
    unit, and a point per run that has the measure (value in that unit, date, status: draw faulted runs
    marked). `falls` is a series in falls per run. `normative` is null unless a published band exists (then
    it carries its source)."""
    if from_date is not None and to_date is not None and to_date < from_date:
        raise InvalidFieldError("to_date", str(to_date), f"must not be before from_date {from_date}")
    read_patient(session=session, patient_id=patient_id, actor_id=user.id)
    twin = request.app.state.twin
    runs = [_run_entry(session, run, twin) for run in _runs_of(session, patient_id, from_date, to_date, limit)]

    def point(run: dict[str, Any], value: float) -> dict[str, Any]:
        return {
            "run_id": run["run_id"],
            "date": run["date"],
            "started_at": run["started_at"],
            "value": value,
            "status": run["status"],
        }

    series = [
        {
            "key": key,
            "label": label,
            "unit": unit,
            "points": [point(run, run["sway"][field] * factor) for run in runs if run["sway"] is not None],
            "normative": NORMATIVE_BANDS.get(key),
        }
        for key, label, unit, field, factor in TREND_SERIES
    ]
    series.append(
        {
            "key": "falls",
            "label": "Falls",
            "unit": "falls per run",
            "points": [point(run, float(run["falls"])) for run in runs],
            "normative": None,
        }
    )
    return {
        "patient_id": patient_id,
        "method": {
            "definitions": "Prieto TE, Myklebust JB, Hoffmann RG, Lovett EG, Myklebust BM (1996). Measures of "
            "postural steadiness: differences between healthy young and elderly adults. IEEE Trans Biomed Eng "
            "43(9):956-966",
            "cop": "net centre of pressure of both plates in the stance frame, over the longest loaded stretch of "
            f"the run in motion, at least {MIN_WINDOW_S:g} s (shorter runs are not measured)",
            "min_window_s": MIN_WINDOW_S,
            "filter": {
                "type": "Butterworth low-pass, zero phase",
                "order": COP_LOWPASS_ORDER,
                "cutoff_hz": COP_LOWPASS_CUTOFF_HZ,
            },
            "ellipse": "95 % prediction ellipse (holds 95 % of the COP samples), not the confidence ellipse",
            "normative": "none: no published band for training on moving platforms could be verified",
        },
        "runs": runs,
        "series": series,
    }
