"""Scheduling requests and answers. Times are timezone-aware ISO 8601 (`start`), or a clinic-local wall
time without offset (`start_local`, read in SSP_REHAB_TIMEZONE); they are stored in UTC and answered in
both UTC and clinic-local time."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Literal

from pydantic import (
    AwareDatetime,
    ConfigDict,
    Field,
    NaiveDatetime,
    StringConstraints,
    field_validator,
    model_validator,
)

from server.api_types import MAX_ID, LongText, RequestModel, ResponseModel

RobotName = Annotated[str, StringConstraints(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.-]+$")]
DurationS = Annotated[int, Field(ge=60, le=4 * 3600, description="Booked length, s (1 min to 4 h).")]
RecordId = Annotated[int, Field(ge=1, le=MAX_ID)]
EARLIEST_START = dt.datetime(2000, 1, 1, tzinfo=dt.UTC)
LATEST_START = dt.datetime(2100, 1, 1, tzinfo=dt.UTC)


def _start_in_range(value: dt.datetime | None) -> dt.datetime | None:
    # Naive local times are compared as if UTC: the range is a sanity bound, not a precise limit.
    if value is not None and not EARLIEST_START <= value.replace(tzinfo=value.tzinfo or dt.UTC) < LATEST_START:
        raise ValueError(f"must lie between {EARLIEST_START:%Y-%m-%d} and {LATEST_START:%Y-%m-%d}")
    return value


StartLocal = Annotated[
    NaiveDatetime | None,
    Field(description="Clinic-local wall time without offset (e.g. 2031-03-04T09:00), instead of `start`."),
]


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
    start: AwareDatetime | None = Field(None, description="With its UTC offset; or give `start_local`.")
    start_local: StartLocal = None
    duration_s: DurationS
    notes: LongText = ""
    recurrence: Recurrence | None = None

    _check_start = field_validator("start", "start_local")(_start_in_range)

    @model_validator(mode="after")
    def _one_start(self) -> ScheduleCreate:
        if (self.start is None) == (self.start_local is None):
            raise ValueError("give exactly one of start and start_local")
        return self

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
    start_local: StartLocal = None
    duration_s: DurationS | None = None
    robot: RobotName | None = None
    therapist_id: RecordId | None = None
    prescription_version: RecordId | None = None
    status: Literal["scheduled", "cancelled", "completed"] | None = None
    notes: LongText | None = None

    _check_start = field_validator("start", "start_local")(_start_in_range)

    @model_validator(mode="after")
    def _at_most_one_start(self) -> ScheduleUpdate:
        if self.start is not None and self.start_local is not None:
            raise ValueError("give exactly one of start and start_local")
        return self

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
    start: dt.datetime = Field(description="UTC.")
    end: dt.datetime = Field(description="UTC.")
    start_local: dt.datetime = Field(description="Clinic-local time with its UTC offset.")
    end_local: dt.datetime = Field(description="Clinic-local time with its UTC offset.")
    timezone: str = Field(description="The clinic's IANA time zone of the local times.")
    duration_s: int
    status: str
    series_id: int | None
    notes: str
    plan: PlanStateOut | None = Field(
        None, description="Its plan on this console's robot; null when no robot daemon answers or it is booked "
        "on another robot (only the single-session answers carry it)."
    )


class PlanStateOut(ResponseModel):
    """The booking's plan on its robot: built and checked ahead, so that Start plays it at once."""

    state: Literal["planning", "ready", "refused", "stale"] = Field(
        description="planning: being built (see progress); ready: checked, Start plays it; refused: the check "
        "refused it (see reason); stale: the robot, its settings or the patient changed since, it is made again"
    )
    progress: float = Field(ge=0.0, le=1.0, description="Fraction built, 0–1.")
    reason: str | None = Field(description="Why the check refused it: segment, time, limit and value.")
    plan_id: str | None = Field(description="The stored plan's key (a hash of everything it is made from).")


class WeekBookingOut(ScheduledSessionOut):
    patient_name: str
    patient_identifier: str
    run_count: int
    last_run_outcome: str | None
    in_care: bool = Field(
        True,
        description="false: the patient is not in your care; the booking shows only when the robot and "
        "therapist are busy (no name, record number, notes or runs).",
    )


class WeekOut(ResponseModel):
    """One clinic-local week of bookings, with what the week view shows, in one answer."""

    timezone: str
    start_local: dt.datetime
    end_local: dt.datetime
    previous_week: dt.date = Field(description="Monday of the previous clinic-local week.")
    next_week: dt.date = Field(description="Monday of the next clinic-local week.")
    bookings: list[WeekBookingOut]
