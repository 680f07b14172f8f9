"""Patient requests and answers. Anthropometrics in SI: height in metres, body mass in kilograms."""

from __future__ import annotations

import datetime as dt
from typing import Annotated, Any, Literal

from pydantic import ConfigDict, Field, field_validator

from server.api_types import Label, LongText, Name, OptionalName, RequestModel, ResponseModel

Sex = Literal["female", "male", "other", "unknown"]
AffectedSide = Literal["left", "right", "both", "none"]
EARLIEST_BIRTH_DATE = dt.date(1900, 1, 1)

EXAMPLE: dict[str, Any] = {
    "identifier": "MRN-0001",
    "name": "Alex Example",
    "date_of_birth": "1956-04-12",
    "sex": "female",
    "height_m": 1.68,
    "body_mass_kg": 64.0,
    "diagnosis": "stroke",
    "affected_side": "left",
    "contraindications": "no yaw perturbations above 10 deg",
    "notes": "uses a cane outdoors",
}

HeightM = Annotated[float, Field(gt=0.5, le=2.5, description="Standing height, m.")]
BodyMassKg = Annotated[float, Field(gt=10.0, le=250.0, description="Body mass, kg (robot rated load: 250 kg).")]


def _birth_date_in_range(value: dt.date | None) -> dt.date | None:
    if value is not None and not EARLIEST_BIRTH_DATE <= value <= dt.date.today():
        raise ValueError(f"must lie between {EARLIEST_BIRTH_DATE} and today")
    return value


class PatientCreate(RequestModel):
    identifier: Label = Field(description="The clinic's record number; unique.")
    name: Name
    date_of_birth: dt.date
    sex: Sex
    height_m: HeightM
    body_mass_kg: BodyMassKg
    diagnosis: OptionalName = ""
    affected_side: AffectedSide = "none"
    contraindications: LongText = ""
    notes: LongText = ""

    model_config = ConfigDict(json_schema_extra={"examples": [EXAMPLE]})

    _check_birth = field_validator("date_of_birth")(_birth_date_in_range)


class PatientUpdate(RequestModel):
    identifier: Label | None = None
    name: Name | None = None
    date_of_birth: dt.date | None = None
    sex: Sex | None = None
    height_m: HeightM | None = None
    body_mass_kg: BodyMassKg | None = None
    diagnosis: OptionalName | None = None
    affected_side: AffectedSide | None = None
    contraindications: LongText | None = None
    notes: LongText | None = None
    archived: bool | None = Field(
        None, description="true archives the record (it leaves the lists), false restores it."
    )
    expected_version: int | None = Field(
        None,
        ge=1,
        le=2**31 - 1,
        description="The version this change is based on, for clients that cannot send If-Match (one is needed).",
    )

    model_config = ConfigDict(
        json_schema_extra={"examples": [{"body_mass_kg": 63.0, "notes": "reassessed", "expected_version": 1}]}
    )

    _check_birth = field_validator("date_of_birth")(_birth_date_in_range)


class PatientOut(ResponseModel):
    id: int
    identifier: str
    name: str
    date_of_birth: dt.date
    sex: Sex
    height_m: float
    body_mass_kg: float
    diagnosis: str
    affected_side: AffectedSide
    contraindications: str
    notes: str
    created_at: dt.datetime
    updated_at: dt.datetime
    archived_at: dt.datetime | None = None
    version: int = Field(description="Changes send it back (If-Match or expected_version); the ETag carries it too.")


class CareTeamAdd(RequestModel):
    user_id: int = Field(ge=1, le=2**31 - 1, description="The clinician to add to the patient's care team.")

    model_config = ConfigDict(json_schema_extra={"examples": [{"user_id": 2}]})


class CareTeamMemberOut(ResponseModel):
    user_id: int
    username: str
    full_name: str
    role: str
    added_by_id: int | None
    added_at: dt.datetime
