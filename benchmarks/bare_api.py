"""The bench's same-run baseline (issue 15 §4): bare FastAPI + SQLAlchemy endpoints doing the product's
queries for `GET /patients?limit=50` and the clinic-local week, with the same response models, but no
authentication, no audit, no middleware. Served by uvicorn like the product:

    SSP_REHAB_DATABASE_URL=... uvicorn benchmarks.bare_api:create_bare_app --factory
"""

import datetime as dt
import os
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, FastAPI, Query
from sqlalchemy import select
from sqlalchemy.orm import Session, sessionmaker

from server.db import create_database_engine, load_models


def create_bare_app() -> FastAPI:
    from server.patients.models import Patient
    from server.patients.schemas import PatientOut
    from server.scheduling.service import week_query

    load_models()
    engine = create_database_engine(os.environ["SSP_REHAB_DATABASE_URL"])
    factory = sessionmaker(bind=engine, expire_on_commit=False)
    app = FastAPI()

    def session() -> Iterator[Session]:
        with factory() as opened:
            yield opened

    SessionDep = Annotated[Session, Depends(session)]

    @app.get("/api/v1/patients", response_model=list[PatientOut])
    def patients(db: SessionDep, limit: Annotated[int, Query(ge=1, le=500)] = 100) -> list[PatientOut]:
        rows = db.scalars(select(Patient).order_by(Patient.name, Patient.id).limit(limit))
        return [PatientOut.model_validate(row) for row in rows]

    @app.get("/api/v1/schedule/week")
    def week(db: SessionDep, day: dt.date, robot: str | None = None) -> list[dict[str, object]]:
        # The product's own query (server.scheduling.service.week_query), for one UTC week.
        monday = dt.datetime.combine(day - dt.timedelta(days=day.weekday()), dt.time(0), tzinfo=dt.UTC)
        rows = db.execute(week_query(monday, monday + dt.timedelta(days=7), robot))
        return [
            {"id": booking.id, "start": booking.start_utc, "end": booking.end_utc, "robot": booking.robot,
             "patient_id": booking.patient_id, "patient_name": name, "patient_identifier": identifier,
             "prescription_id": prescription_id, "prescription_version": version, "status": booking.status,
             "run_count": run_count, "last_run_outcome": outcome}
            for booking, prescription_id, version, name, identifier, run_count, outcome in rows
        ]  # fmt: skip

    @app.get("/api/v1/health")
    def health() -> dict[str, str]:
        return {"status": "ok"}

    return app
