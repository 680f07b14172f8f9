"""Clinic-local time: the clinic's IANA zone, local wall times that exist exactly once, recurring series
expanded in local time (dateutil.rrule), and the clinic-local week.

Bookings are stored in UTC, but a clinic lives by its wall clock: a weekly 09:00 session stays at 09:00
after the clocks change. A wall time that does not exist (the spring gap) or exists twice (the autumn
overlap) is refused with the field, the value and why, never shifted to a neighbouring time.
"""

from __future__ import annotations

import datetime as dt
import functools
import os
from pathlib import Path
from zoneinfo import ZoneInfo, ZoneInfoNotFoundError, available_timezones

from dateutil.rrule import DAILY, WEEKLY, rrule

from server.errors import InvalidFieldError

RRULE_FREQUENCIES = {"daily": DAILY, "weekly": WEEKLY}
ZONEINFO_ROOTS = ("/usr/share/zoneinfo/", "/usr/lib/zoneinfo/", "/usr/share/lib/zoneinfo/")


def machine_zone_name() -> str:
    """The machine's IANA zone: $TZ, else /etc/localtime's link target, else /etc/timezone, else UTC."""
    candidates = [os.environ.get("TZ", "").lstrip(":")]
    localtime = Path("/etc/localtime")
    if localtime.is_symlink():
        target = str(localtime.resolve())
        candidates += [target[len(root) :] for root in ZONEINFO_ROOTS if target.startswith(root)]
    timezone_file = Path("/etc/timezone")
    if timezone_file.exists():
        candidates.append(timezone_file.read_text().strip())
    for name in candidates:
        if name and is_zone_name(name):
            return name
    return "UTC"


@functools.cache
def _zone_names() -> frozenset[str]:
    return frozenset(available_timezones()) | {"UTC"}  # reads the tz database once per process


def is_zone_name(name: str) -> bool:
    if name not in _zone_names():
        return False
    try:
        ZoneInfo(name)
    except (ZoneInfoNotFoundError, ValueError):
        return False
    return True


def _describe(local: dt.datetime) -> str:
    return f"{local:%Y-%m-%d %H:%M}"


def to_utc(local: dt.datetime, zone: ZoneInfo, *, field: str, what: str = "") -> dt.datetime:
    """A naive clinic-local wall time as UTC, refused if it falls in a DST gap or overlap."""
    assert local.tzinfo is None
    earlier = local.replace(tzinfo=zone, fold=0)
    later = local.replace(tzinfo=zone, fold=1)
    if earlier.utcoffset() == later.utcoffset():
        return earlier.astimezone(dt.UTC)
    prefix = f"{what}: " if what else ""
    offsets = [moment.utcoffset() or dt.timedelta() for moment in (earlier, later)]
    shift_h = abs(offsets[1] - offsets[0]) / dt.timedelta(hours=1)
    if earlier.astimezone(dt.UTC).astimezone(zone).replace(tzinfo=None) != local:
        reason = (
            f"{prefix}{_describe(local)} does not exist in {zone.key}: the clocks go forward by {shift_h:g} h"
            " at the daylight-saving change; choose a time before or after the skipped hour"
        )
    else:
        first, second = sorted((earlier.astimezone(dt.UTC), later.astimezone(dt.UTC)))
        reason = (
            f"{prefix}{_describe(local)} is ambiguous in {zone.key}: it occurs twice when the clocks go back by"
            f" {shift_h:g} h (at {first:%H:%M} and at {second:%H:%M} UTC); choose a time outside the repeated hour"
        )
    raise InvalidFieldError(field, _describe(local), reason)


def wall_time(instant: dt.datetime, zone: ZoneInfo, *, field: str) -> dt.datetime:
    """The naive clinic-local wall time of an aware instant, refused if that wall time is ambiguous."""
    local = instant.astimezone(zone).replace(tzinfo=None)
    to_utc(local, zone, field=field)
    return local


def local_occurrences(
    first: dt.datetime, frequency: str, interval: int, count: int, zone: ZoneInfo, *, field: str
) -> list[dt.datetime]:
    """The UTC starts of a series whose occurrences keep the first one's local wall time (RFC 5545 RRULE
    expanded in local time). Any occurrence in a DST gap or overlap refuses the whole series."""
    wall_times = rrule(RRULE_FREQUENCIES[frequency], interval=interval, count=count, dtstart=first)
    return [
        to_utc(local, zone, field=field, what=f"occurrence {index + 1} of {count}")
        for index, local in enumerate(wall_times)
    ]


def week_bounds(day: dt.date, zone: ZoneInfo) -> tuple[dt.datetime, dt.datetime]:
    """The clinic-local week (Monday 00:00 to the next Monday 00:00) holding `day`, as aware local times.
    A week with a DST change is 167 or 169 hours long."""
    monday = day - dt.timedelta(days=day.weekday())
    start = dt.datetime.combine(monday, dt.time(0), tzinfo=zone)
    end = dt.datetime.combine(monday + dt.timedelta(days=7), dt.time(0), tzinfo=zone)
    return start, end
