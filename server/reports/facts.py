"""What a report states, gathered from the records: the run, its patient and prescription version, the
outcome and events in time into the run, falls, the Prieto sway measures, the cue quality, the SOAP notes
and the acknowledgement. SI units here; the PDF shows mm, cm², degrees."""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from core.fidelity import FidelityScales, fidelity_of_signals, platform_specific_force
from core.robot import TwinRobot
from core.sampling import on_uniform_grid
from core.vestibular import VestibularModel
from server.errors import ConflictError
from server.patients.models import Patient
from server.prescriptions.models import Prescription, PrescriptionVersion
from server.reviews.schemas import RunReviewOut
from server.reviews.service import review_of
from server.robotd.models import SessionEvent, SessionRun
from server.robotd.runs import get_run
from server.scheduling.models import ScheduledSession
from server.sessions.balance import run_balance
from server.sessions.logs import telemetry_columns
from server.users.models import User

AXES = ("x", "y", "z")
MIN_SAMPLES_FOR_QUALITY = 16
# The delivered motion's smoothing: a cubic Savitzky–Golay fit over this window. It passes the cues (a few Hz
# at most) and takes out what a sample's time stamp jitter (tenths of a millisecond) adds to a derivative.
DELIVERED_WINDOW_S = 0.101
DELIVERED_POLYORDER = 3


def delivered_motion(columns: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """What the platform delivered (issue 22 §6): the measured stance pose (forward kinematics of the measured
    sliders), resampled onto a uniform grid (core.sampling), then fitted by
    a cubic Savitzky–Golay filter over `DELIVERED_WINDOW_S`, whose fit gives the pose, its velocity and its
    acceleration at once; back at the samples' times, each (6, N). None when the run is too short for the
    window. Before, the commanded pose was differentiated twice by finite differences over the stamps, and
    stamp jitter read as ±100 m/s² against a 0.5 m/s² cue."""
    from scipy.signal import savgol_filter

    time_s = np.asarray(columns["time_s"], dtype=float)
    measured = np.asarray(columns["measured_stance_pose"], dtype=float)
    grid, period_s, on_grid = on_uniform_grid(time_s, measured)
    window = max(DELIVERED_POLYORDER + 2, round(DELIVERED_WINDOW_S / period_s)) | 1  # odd
    if len(grid) < window:
        return None
    fitted = [
        savgol_filter(on_grid, window, DELIVERED_POLYORDER, deriv=deriv, delta=period_s, axis=0) for deriv in (0, 1, 2)
    ]
    return tuple(  # type: ignore[return-value]
        np.array([np.interp(time_s, grid, values[:, axis]) for axis in range(values.shape[1])]) for values in fitted
    )


@dataclass
class EventFact:
    kind: str
    time_into_run_s: float | None
    utc: dt.datetime
    detector: str | None
    details: dict[str, Any]


@dataclass
class RunFacts:
    run: SessionRun
    patient: Patient
    prescription_name: str
    version: PrescriptionVersion
    events: list[EventFact]
    review: RunReviewOut
    sway: dict[str, float] | None = None
    cue_quality: dict[str, Any] | None = None
    series: dict[str, np.ndarray] = field(default_factory=dict)  # time into the run, COP, cue, loads
    user_names: dict[int, str] = field(default_factory=dict)  # who acknowledged, who wrote the notes

    @property
    def falls(self) -> list[EventFact]:
        return [event for event in self.events if event.kind == "fall"]

    @property
    def duration_s(self) -> float | None:
        if self.run.ended_at is None:
            return None
        return (self.run.ended_at - self.run.started_at).total_seconds()


def time_into_run(event: SessionEvent, start: SessionEvent | None, run: SessionRun) -> float | None:
    """The worker clock minus the run's start on the same clock; the UTC difference if either is unknown."""
    if start is not None and start.tick_time_s is not None and event.tick_time_s is not None:
        return float(event.tick_time_s - start.tick_time_s)
    return (event.utc - run.started_at).total_seconds()


def cue_quality(columns: dict[str, np.ndarray]) -> dict[str, Any] | None:
    """How well the platform delivered the cue (paper §4.2): the perceived specific-force error per axis
    through the otolith model (RMS and peak, m/s²), the perception objective in thresholds, and the
    correlation of commanded and delivered specific force on the horizontal axes."""
    time_s = np.asarray(columns["time_s"], dtype=float)
    if len(time_s) < MIN_SAMPLES_FOR_QUALITY or np.any(np.diff(time_s) <= 0):
        return None
    period_s = float(np.median(np.diff(time_s)))
    motion = delivered_motion(columns)
    if motion is None:
        return None
    pose, velocity, acceleration = motion
    cue_force = np.asarray(columns["cue_specific_force_m_s2"], dtype=float).T
    cue_rate = np.asarray(columns["cue_angular_velocity_rad_s"], dtype=float).T
    metrics = fidelity_of_signals(
        pose, velocity, acceleration, cue_force, cue_rate, VestibularModel(sample_period_s=period_s), FidelityScales()
    )
    delivered = platform_specific_force(pose, acceleration)
    correlation = {}
    for index, axis in enumerate(AXES[:2]):
        commanded = cue_force[index]
        correlation[axis] = (
            float(np.corrcoef(commanded, delivered[index])[0, 1])
            if np.std(commanded) > 1e-9 and np.std(delivered[index]) > 1e-9
            else None
        )
    return {
        "perceived_error_rms_m_s2": dict(
            zip(AXES, np.asarray(metrics.specific_force_error_rms_m_s2).tolist(), strict=True)
        ),
        "perceived_error_peak_m_s2": dict(
            zip(AXES, np.asarray(metrics.specific_force_error_peak_m_s2).tolist(), strict=True)
        ),
        "perception_error_thresholds": float(metrics.perception_error),
        "correlation": correlation,
        "cue_rms_m_s2": dict(zip(AXES, np.sqrt(np.mean(cue_force**2, axis=-1)).tolist(), strict=True)),
        "delivered_m_s2": delivered,
    }


def run_facts(*, session: Session, run_id: int, twin: TwinRobot) -> RunFacts:
    run = get_run(session=session, run_id=run_id)
    booking = session.get(ScheduledSession, run.scheduled_session_id)
    version = session.get(PrescriptionVersion, run.prescription_version_id)
    if booking is None or version is None:
        raise ConflictError(f"run {run_id} has lost its booking or prescription version")
    patient = session.get(Patient, booking.patient_id)
    prescription = session.get(Prescription, version.prescription_id)
    assert patient is not None and prescription is not None  # foreign keys with RESTRICT
    stored = session.scalars(select(SessionEvent).where(SessionEvent.run_id == run.id).order_by(SessionEvent.id)).all()
    start = next((event for event in stored if event.kind == "start"), None)
    events = [EventFact(e.kind, time_into_run(e, start, run), e.utc, e.detector, dict(e.details)) for e in stored]
    review = review_of(session, run)
    people = {review.acknowledgement.user_id if review.acknowledgement else None, review.notes.author_id} - {None}
    user_names = {
        user.id: user.full_name or user.username for user in session.scalars(select(User).where(User.id.in_(people)))
    }
    facts = RunFacts(run, patient, prescription.name, version, events, review, user_names=user_names)
    try:
        columns = telemetry_columns(session=session, run_id=run.id)
    except ConflictError:
        return facts  # nothing recorded (stopped before the first sample)
    facts.sway = run_balance(columns, twin)
    quality = cue_quality(columns)
    origin = (
        float(start.tick_time_s) if start is not None and start.tick_time_s is not None else float(columns["time_s"][0])
    )
    facts.series = {
        "time_s": np.asarray(columns["time_s"], dtype=float) - origin,
        "cop_m": np.asarray(columns["plate_cop_m"], dtype=float),
        "plate_force_z_n": np.asarray(columns["plate_force_z_n"], dtype=float),
        "harness_load_n": np.asarray(columns["harness_load_n"], dtype=float),
        "cue_m_s2": np.asarray(columns["cue_specific_force_m_s2"], dtype=float),
    }
    if quality is not None:
        facts.series["delivered_m_s2"] = quality.pop("delivered_m_s2").T
        facts.cue_quality = quality
    return facts


@dataclass
class ProgressRow:
    run: SessionRun
    prescription_name: str
    version: int
    falls: int
    sway: dict[str, float] | None
    perception_error: float | None


def progress_rows(
    *, session: Session, patient_id: int, twin: TwinRobot, start: dt.date | None, end: dt.date | None, limit: int
) -> list[ProgressRow]:
    """The patient's runs between two dates (inclusive), oldest first, with their falls and measures."""
    query = (
        select(SessionRun, PrescriptionVersion, Prescription.name)
        .join(ScheduledSession, ScheduledSession.id == SessionRun.scheduled_session_id)
        .join(PrescriptionVersion, PrescriptionVersion.id == SessionRun.prescription_version_id)
        .join(Prescription, Prescription.id == PrescriptionVersion.prescription_id)
        .where(ScheduledSession.patient_id == patient_id, SessionRun.state == "ended")
        .order_by(SessionRun.started_at.desc())
        .limit(limit)
    )
    if start is not None:
        query = query.where(SessionRun.started_at >= dt.datetime.combine(start, dt.time(), dt.UTC))
    if end is not None:
        query = query.where(SessionRun.started_at < dt.datetime.combine(end + dt.timedelta(days=1), dt.time(), dt.UTC))
    rows = []
    for run, version, name in reversed(session.execute(query).all()):
        falls = len(
            session.scalars(
                select(SessionEvent.id).where(SessionEvent.run_id == run.id, SessionEvent.kind == "fall")
            ).all()
        )
        sway = quality = None
        try:
            columns = telemetry_columns(session=session, run_id=run.id)
            sway = run_balance(columns, twin)
            measured = cue_quality(columns)
            quality = measured["perception_error_thresholds"] if measured else None
        except ConflictError:
            pass
        rows.append(ProgressRow(run, name, version.version, falls, sway, quality))
    return rows
