"""Scheduling requests and answers. Times are timezone-aware ISO 8601; they are stored in UTC."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Literal

from pydantic import AwareDatetime, ConfigDict, Field, StringConstraints, field_validator

from server.api_types import MAX_ID, LongText, RequestModel, ResponseModel

RobotName = Annotated[str, StringConstraints(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]
DurationS = Annotated[int, Field(ge=60, le=4 * 3600, description="Booked length, s (1 min to 4 h).")]
RecordId = Annotated[int, Field(ge=1, le=MAX_ID)]
EARLIEST_START = dt.datetime(2000, 1, 1, tzinfo=dt.UTC)
LATEST_START = dt.datetime(2100, 1, 1, tzinfo=dt.UTC)


def _start_in_range(value: dt.datetime | None) -> dt.datetime | None:
    if value is not None and not EARLIEST_START <= value < LATEST_START:
        raise ValueError(f"must lie between {EARLIEST_START:%Y-%m-%d} and {LATEST_START:%Y-%m-%d}")
    return value


class Recurrence(RequestModel):
    frequency: Literal["daily", "weekly"]
    interval: int = Field(1, ge=1, le=52, description="Every `interval` days or weeks.")
    count: int = Field(ge=2, le=104, description="Number of occurrences, the first included.")


class ScheduleCreate(RequestModel):
    patient_id: RecordId
    prescription_id: RecordId
    prescription_version: RecordId | None = Field(None, description="Default: the prescription's latest version.")
    robot: RobotName
    therapist_id: RecordId | None = Field(None, description="Default: the user making the booking.")
    start: AwareDatetime
    duration_s: DurationS
    notes: LongText = ""
    recurrence: Recurrence | None = None

    _check_start = field_validator("start")(_start_in_range)

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [
                {
                    "patient_id": 1,
                    "prescription_id": 1,
                    "robot": "twin-1",
                    "start": "2031-03-04T09:00:00+01:00",
                    "duration_s": 1800,
                    "notes": "",
                    "recurrence": {"frequency": "weekly", "interval": 1, "count": 6},
                }
            ]
        }
    )


class ScheduleUpdate(RequestModel):
    start: AwareDatetime | None = None
    duration_s: DurationS | None = None
    robot: RobotName | None = None
    therapist_id: RecordId | None = None
    prescription_version: RecordId | None = None
    status: Literal["scheduled", "cancelled", "completed"] | None = None
    notes: LongText | None = None

    _check_start = field_validator("start")(_start_in_range)

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"start": "2031-03-05T10:00:00+01:00", "duration_s": 2400}]}
    )


class ScheduledSessionOut(ResponseModel):
    id: int
    patient_id: int
    prescription_id: int
    prescription_version: int
    prescription_version_id: int
    robot: str
    therapist_id: int
    start: dt.datetime
    end: dt.datetime
    duration_s: int
    status: str
    series_id: int | None
    notes: str
