"""The base of every input model (prescriptions, API request bodies): unknown fields and numbers that are
not finite or not normal are refused at the field that holds them, never passed on to a filter design or
a solver (a subnormal cut-off of 5e-324 Hz made scipy's Butterworth design raise: issue 20, defect 9).

Physical ranges are each field's own (`Field(ge=..., le=...)`); this is the rule every float shares.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping
from typing import Any

from pydantic import BaseModel, ConfigDict, field_validator
from pydantic_core import PydanticCustomError

SMALLEST_NORMAL = sys.float_info.min  # 2.2250738585072014e-308
NOT_NORMAL = (
    f"must be a finite number, 0 or of magnitude ≥ {SMALLEST_NORMAL!r} (a subnormal number has lost its precision)"
)


def is_normal_or_zero(value: float) -> bool:
    return math.isfinite(value) and (value == 0.0 or abs(value) >= SMALLEST_NORMAL)


def _refuse_abnormal(value: Any) -> None:
    if isinstance(value, float) and not is_normal_or_zero(value):
        raise PydanticCustomError("float_not_normal", NOT_NORMAL, {"limit": NOT_NORMAL})
    if isinstance(value, list | tuple | set | frozenset):
        for item in value:
            _refuse_abnormal(item)
    elif isinstance(value, Mapping):
        for item in value.values():
            _refuse_abnormal(item)


class StrictModel(BaseModel):
    """Unknown fields, NaN, ±inf and subnormal floats are refused, each at its field."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _normal_numbers(cls, value: Any) -> Any:
        _refuse_abnormal(value)  # nested models have run this check on their own fields already
        return value
