"""`GET /runs/{id}/report.pdf` and `GET /patients/{id}/progress.pdf`."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Query, Request, Response
from sqlalchemy.orm import Session

from core.robot import TwinRobot
from server.api_types import IdPath
from server.audit import service as audit
from server.auth.access import ObjectAccess
from server.auth.dependencies import CurrentUser, current_user
from server.db import SessionDep, writes
from server.errors import InvalidFieldError
from server.patients.service import read_patient
from server.reports.facts import RunFacts, progress_rows, run_facts
from server.reports.pdf import progress_report_pdf, run_report_pdf

router = APIRouter(tags=["reports"], dependencies=[Depends(current_user), ObjectAccess])
PDF: dict[int | str, dict[str, Any]] = {200: {"content": {"application/pdf": {}}, "description": "The report (PDF)"}}


@writes
def _audited_run_facts(*, session: Session, run_id: int, twin: TwinRobot, user_id: int) -> RunFacts:
    facts = run_facts(session=session, run_id=run_id, twin=twin)
    audit.record(session=session, user_id=user_id, action="report", resource_type="session_run", resource_id=run_id,
                 details={"patient_id": facts.patient.id})  # fmt: skip
    return facts


@router.get("/runs/{run_id}/report.pdf", response_class=Response, responses=PDF)
def run_report(run_id: IdPath, request: Request, session: SessionDep, user: CurrentUser) -> Response:
    """The run's report: patient, prescription version, outcome, events and falls in time into the run, the
    sway measures, the cue quality, charts and the therapist's SOAP notes."""
    facts = _audited_run_facts(session=session, run_id=run_id, twin=request.app.state.twin, user_id=user.id)
    pdf = run_report_pdf(facts)
    return Response(pdf, media_type="application/pdf",
                    headers={"Content-Disposition": f'inline; filename="run-{run_id}-report.pdf"'})  # fmt: skip


@router.get("/patients/{patient_id}/progress.pdf", response_class=Response, responses=PDF)
def progress_report(
    patient_id: IdPath,
    request: Request,
    session: SessionDep,
    user: CurrentUser,
    start: Annotated[dt.date | None, Query(alias="from", description="First day (inclusive).")] = None,
    end: Annotated[dt.date | None, Query(alias="to", description="Last day (inclusive).")] = None,
    limit: Annotated[int, Query(ge=1, le=200, description="Most recent runs in the period.")] = 50,
) -> Response:
    """The patient's runs over dates: outcome, falls, sway measures and cue quality, one chart per measure."""
    if start is not None and end is not None and end < start:
        raise InvalidFieldError("to", end.isoformat(), f"must be on or after from = {start.isoformat()}")
    patient = read_patient(session=session, patient_id=patient_id, actor_id=user.id)
    twin = request.app.state.twin
    rows = progress_rows(session=session, patient_id=patient_id, twin=twin, start=start, end=end, limit=limit)
    pdf = progress_report_pdf(patient, rows, start, end)
    return Response(pdf, media_type="application/pdf",
                    headers={"Content-Disposition": f'inline; filename="progress-{patient.id}.pdf"'})  # fmt: skip
