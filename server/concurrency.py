"""Optimistic concurrency for versioned records (patients, prescriptions): the answer's `ETag` is the record's
version; a change names the version it was based on (`If-Match`, or `expected_version` in the body) and is
refused with 412 when someone changed the record since, or 428 when it names none (docs/service.md)."""

from __future__ import annotations

from typing import Annotated

from fastapi import Header, Response

from server.errors import InvalidFieldError, PreconditionRequiredError

IfMatch = Annotated[
    str | None,
    Header(
        alias="If-Match",
        max_length=100,
        description='The ETag of the GET your change is based on (e.g. "3"); or send expected_version in the body.',
    ),
]


def etag(version: int) -> str:
    return f'"{version}"'


def with_etag(response: Response, version: int) -> None:
    response.headers["ETag"] = etag(version)


def _parse_if_match(value: str) -> int:
    tag = value.strip().removeprefix("W/").strip().strip('"')
    if not tag.isdigit() or not 1 <= int(tag) <= 2**31 - 1:
        raise InvalidFieldError("If-Match", value, 'must be the ETag of a GET of this record, e.g. "3"')
    return int(tag)


def expected_version(if_match: str | None, body_version: int | None, *, resource: str, resource_id: int) -> int:
    """The version a change is based on; 428 when neither `If-Match` nor `expected_version` names one."""
    header_version = _parse_if_match(if_match) if if_match else None
    if header_version is not None and body_version is not None and header_version != body_version:
        raise InvalidFieldError("expected_version", body_version, f"differs from If-Match {if_match}")
    version = header_version if header_version is not None else body_version
    if version is None:
        raise PreconditionRequiredError(resource, resource_id)
    return version
