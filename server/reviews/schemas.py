"""Review requests and answers: the acknowledgement of a stop that moved the patient, and a run's SOAP notes."""

from __future__ import annotations

import datetime as dt

from pydantic import ConfigDict, Field

from server.api_types import LongText, RequestModel, ResponseModel


class AcknowledgementIn(RequestModel):
    note: LongText = Field(default="", description="What was checked or done before the next run (optional).")

    model_config = ConfigDict(json_schema_extra={"examples": [{"note": "Patient attended to; harness checked."}]})


class AcknowledgementOut(ResponseModel):
    event_id: int
    run_id: int
    outcome: str
    user_id: int | None
    utc: dt.datetime
    note: str


class RunNotesIn(RequestModel):
    subjective: LongText = Field(default="", description="S: what the patient reports (fatigue, dizziness, pain).")
    objective: LongText = Field(default="", description="O: what the therapist observed or measured.")
    assessment: LongText = Field(default="", description="A: the therapist's interpretation.")
    plan: LongText = Field(default="", description="P: the next step (progression, changes to the prescription).")

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "subjective": "Mild dizziness after segment 2.",
                    "objective": "One step to the right at 25 s.",
                    "assessment": "Lateral control improving.",
                    "plan": "Same amplitude, shorter segments.",
                }
            ]
        }
    )


class RunNotesOut(RunNotesIn):
    run_id: int
    author_id: int | None
    updated_at: dt.datetime | None


class RunReviewOut(ResponseModel):
    run_id: int
    robot: str
    outcome: str | None
    needs_acknowledgement: bool = Field(
        description="The run ended in a stop that moved the patient (emergency stop, interruption, fault, fall, "
        "limit stop) not yet acknowledged."
    )
    acknowledgement: AcknowledgementOut | None
    notes: RunNotesOut
