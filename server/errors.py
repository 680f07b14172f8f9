"""Domain errors raised by the service functions; `server.app` maps them to 404, 409 and 422 answers."""

from __future__ import annotations


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

    def __init__(self, field: str, value: object, limit: str) -> None:
        self.field = field
        self.value = value
        self.limit = limit
        super().__init__(f"{field} = {value!r}: {limit}")


class WorkerUnavailableError(RuntimeError):
    """Run control asked for while no real-time worker (robot) is connected."""
