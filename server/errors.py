"""Domain errors raised by the service functions; `server.app` maps them to 404, 409 and 422 answers."""

from __future__ import annotations

import datetime as dt
from typing import Any


class NotFoundError(LookupError):
    def __init__(self, resource: str, resource_id: object) -> None:
        self.resource = resource
        self.resource_id = resource_id
        super().__init__(f"{resource} {resource_id} does not exist")


class ConflictError(RuntimeError):
    """The request is valid but clashes with what is stored (double booking, duplicate name, wrong state)."""

    def __init__(self, message: str, *, field: str | None = None) -> None:
        self.field = field
        super().__init__(message)


class InvalidFieldError(ValueError):
    """A value that passed the schema but breaks a domain rule; names the field, the value and the limit."""

    def __init__(self, field: str, value: object, limit: str, *, details: dict[str, Any] | None = None) -> None:
        self.field = field
        self.value = value
        self.limit = limit
        self.details = details or {}  # what else the check found (a refused plan's every breach), shown as is
        super().__init__(f"{field} = {value!r}: {limit}")


class WorkerUnavailableError(RuntimeError):
    """Run control asked for while no real-time worker (robot) is connected."""


class PreconditionRequiredError(RuntimeError):
    """A change of a versioned record sent without the version it was based on (428)."""

    def __init__(self, resource: str, resource_id: object) -> None:
        self.resource = resource
        self.resource_id = resource_id
        super().__init__(
            f"{resource} {resource_id}: send the version your change is based on, as the If-Match header with the "
            f'ETag of your GET (e.g. If-Match: "3") or as expected_version in the body, so that no one else\'s '
            "change is overwritten unseen"
        )


class StaleVersionError(RuntimeError):
    """A change based on a version that is no longer the current one (412): someone else changed it since."""

    def __init__(
        self,
        resource: str,
        resource_id: object,
        *,
        expected: int,
        current: int | None,
        changed_by: str | None = None,
        changed_at: dt.datetime | None = None,
    ) -> None:
        self.resource = resource
        self.resource_id = resource_id
        self.expected = expected
        self.current = current
        self.changed_by = changed_by
        self.changed_at = changed_at
        super().__init__(f"{resource} {resource_id} changed since version {expected}")
