"""Prescription requests and answers. What is prescribed is `core.plan.prescription` (the one model of a
prescription, docs/service.md); the requests add the patient, the name and the note."""

from __future__ import annotations

import datetime as dt
from typing import Any

from pydantic import ConfigDict, Field

from core.plan.prescription import PrescriptionBody
from server.api_types import MAX_ID, LongText, Name, RequestModel, ResponseModel

EXAMPLE_SEGMENT: dict[str, Any] = {
    "cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.5},
    "duration_s": 60.0,
    "limits": {"tilt_max_rad": 0.2},
}


class PrescriptionCreate(PrescriptionBody, RequestModel):
    patient_id: int = Field(ge=1, le=MAX_ID)
    name: Name
    note: LongText = ""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [{"patient_id": 1, "name": "Lateral sway, week 1", "segments": [EXAMPLE_SEGMENT], "note": ""}]
        }
    )


class PrescriptionRevise(PrescriptionBody, RequestModel):
    """A new version: the segments replace the previous version's; earlier versions stay as they were. A
    `cueing` or `seed` left out is kept from the current version."""

    name: Name | None = None
    note: LongText = ""
    expected_version: int | None = Field(
        None,
        ge=1,
        le=2**31 - 1,
        description="The version this revision is based on, for clients that cannot send If-Match (one is needed).",
    )

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [{"segments": [EXAMPLE_SEGMENT], "note": "longer washout after review", "expected_version": 1}]
        }
    )


class PrescriptionVersionOut(ResponseModel):
    id: int
    prescription_id: int
    version: int
    content: dict[str, Any]
    note: str
    created_by_id: int | None
    created_at: dt.datetime


class PrescriptionOut(ResponseModel):
    id: int
    patient_id: int
    name: str
    latest_version: int
    created_at: dt.datetime
    current: PrescriptionVersionOut
