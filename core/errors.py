"""The one refusal every layer shares: an invalid value, named by its field, with the limit it broke."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any


class InvalidValueError(ValueError):
    """Refusal of an invalid input; names the field, the value and the limit it broke.

    Subclasses only say where the value came from (robot description, filter parameters, drive
    configuration, …); the message format is the same everywhere so users learn to read it once.
    """

    def __init__(self, field_name: str, value: object, limit: str) -> None:
        self.field = field_name
        self.value = value
        self.limit = limit
        super().__init__(f"{field_name} = {value!r}: {limit}")


def refuse_unknown_fields(cls: type, data: Mapping[str, Any], error: type[InvalidValueError], what: str) -> None:
    """Refuses a settings mapping with a key that is not a field of the dataclass `cls`, naming the first."""
    known = {item.name for item in dataclasses.fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise error(unknown[0], data[unknown[0]], f"unknown {what}; known: {sorted(known)}")
