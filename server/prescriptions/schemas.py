"""Prescription requests and answers (see the agreed prescription format in docs/service.md)."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field

from server.api_types import MAX_ID, LongText, Name, RequestModel, ResponseModel

EXAMPLE_SEGMENT: dict[str, Any] = {
    "cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.5},
    "duration_s": 60.0,
    "limits": {"tilt_max_rad": 0.2},
}


class SegmentIn(RequestModel):
    cue: dict[str, Any] = Field(description='Cue generator spec, e.g. `{"kind": "sine", ...}` (core.cues).')
    duration_s: float = Field(gt=0.0, le=3600.0)
    washout: dict[str, Any] | None = Field(
        None, description="WashoutParameters.to_dict(); default: the set that reproduces paper Section 5."
    )
    limits: dict[str, float] = Field(
        default_factory=dict, description="Overrides of the robot's MotionLimits; they may only tighten them."
    )

    model_config = ConfigDict(json_schema_extra={"examples": [EXAMPLE_SEGMENT]})


Segments = Annotated[list[SegmentIn], Field(min_length=1, max_length=50)]
Cueing = Annotated[
    Literal["classical", "optimal"],
    Field(description="Motion cueing: the paper's classical washout, or optimal cueing planned over the whole "
          "prescription (core.optimal_cueing)."),
]  # fmt: skip


class PrescriptionCreate(RequestModel):
    patient_id: int = Field(ge=1, le=MAX_ID)
    name: Name
    segments: Segments
    cueing: Cueing = "classical"
    note: LongText = ""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [{"patient_id": 1, "name": "Lateral sway, week 1", "segments": [EXAMPLE_SEGMENT], "note": ""}]
        }
    )


class PrescriptionRevise(RequestModel):
    """A new version: the segments replace the previous version's; earlier versions stay as they were."""

    segments: Segments
    cueing: Cueing = "classical"
    name: Name | None = None
    note: LongText = ""

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"segments": [EXAMPLE_SEGMENT], "note": "longer washout after review"}]}
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
