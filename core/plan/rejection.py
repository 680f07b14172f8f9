"""A plan's refusal: where it would break a limit, which limit and by how much.

Apart from the check (`core.plan.check`) so that the processes that only pass a refusal on (the robot
daemon's messages, the stop listener) do not import the check's kernels and scipy.
"""

from __future__ import annotations

from typing import Any


class PrescriptionRejected(ValueError):  # noqa: N818 — the agreed interface name
    """The prescription would exceed a limit: where (segment, time in it) and which limit."""

    def __init__(
        self, segment: int, time_s: float, limit: str, value: float, message: str, details: dict[str, Any] | None = None
    ) -> None:
        self.segment, self.time_s, self.limit, self.value = segment, time_s, limit, value
        # Beyond the first breach: every kinematic limit broken in the segment (by reason, with its stretches)
        # and each robot's singularity report (worst cond(J) and when, every det J sign change).
        self.details = details or {}
        super().__init__(message)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> PrescriptionRejected:
        """The inverse of `to_dict`, every field kept (across the planning process's and the worker's pipes)."""
        fields = ("segment", "time_s", "limit", "value", "message")
        details = {key: value for key, value in data.items() if key not in (*fields, "type")}
        return cls(data["segment"], data["time_s"], data["limit"], data["value"], data["message"], details)

    def to_dict(self) -> dict[str, Any]:
        return {
            "segment": self.segment,
            "time_s": self.time_s,
            "limit": self.limit,
            "value": self.value,
            "message": str(self),
            **self.details,
        }
