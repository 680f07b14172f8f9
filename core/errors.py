"""The one refusal every layer shares: an invalid value, named by its field, with the limit it broke."""

from __future__ import annotations


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
