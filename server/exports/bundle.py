"""Bulk export for a study: many session logs in one zip (issue 6 §5, "by date range and by diagnosis").

The service selects the session runs (its database query does the date-range and diagnosis filter);
this module packs them: one folder per session with `metadata.json` and every chosen format, plus
`index.csv` and `index.json` listing each session's pseudonymised patient id, date, diagnosis and
recording summary. A study bundle leaves the clinic, so a log whose patient record still carries an
identifying field is refused unless the caller explicitly allows identified exports.
"""

from __future__ import annotations

import csv
import io
import zipfile
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, BinaryIO, cast

from server.exports.formats import (
    EXPORT_FORMATS,
    check_format,
    open_zip,
    session_file_stem,
    sidecar,
    write_csv_members,
)
from server.exports.log import RecordedLog, SessionLogError, to_json
from server.exports.metadata import identifying_fields

INDEX_COLUMNS = (
    "session_id",
    "pseudonym_id",
    "started_utc",
    "session_date",
    "diagnosis",
    "affected_side",
    "sex",
    "age_at_session_years",
    "prescription_version",
    "duration_s",
    "sample_count",
    "event_count",
    "event_kinds",
    "folder",
)


def index_row(log: RecordedLog, folder: str) -> dict[str, Any]:
    """One study-index row: who (pseudonymised), when, what diagnosis, and what was recorded."""
    patient = log.metadata.get("patient") or {}
    started = str(log.metadata.get("started_utc", ""))
    kinds = Counter(event["kind"] for event in log.events)
    return {
        "session_id": log.session_id,
        "pseudonym_id": patient.get("pseudonym_id"),
        "started_utc": started or None,
        "session_date": started[:10] or None,
        "diagnosis": patient.get("diagnosis"),
        "affected_side": patient.get("affected_side"),
        "sex": patient.get("sex"),
        "age_at_session_years": patient.get("age_at_session_years"),
        "prescription_version": (log.metadata.get("prescription") or {}).get("version"),
        "duration_s": log.duration_s,
        "sample_count": log.sample_count,
        "event_count": len(log.events),
        "event_kinds": ";".join(f"{kind}:{count}" for kind, count in sorted(kinds.items())),
        "folder": folder,
    }


def _index_csv(rows: Iterable[Mapping[str, Any]]) -> bytes:
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=INDEX_COLUMNS, lineterminator="\n")
    writer.writeheader()
    writer.writerows({key: "" if value is None else value for key, value in row.items()} for row in rows)
    return text.getvalue().encode()


def write_session_folder(archive: zipfile.ZipFile, folder: str, log: RecordedLog, formats: Sequence[str]) -> None:
    """One session's folder: `metadata.json` and each format (the CSV files unzipped into the folder)."""
    if "csv" in formats:
        write_csv_members(archive, f"{folder}/", log)  # includes metadata.json
    else:
        archive.writestr(f"{folder}/metadata.json", to_json(sidecar(log), indent=2))
    for fmt in formats:
        if fmt != "csv":
            writer, _, suffix = check_format(fmt)
            with archive.open(f"{folder}/session{suffix}", "w", force_zip64=True) as member:
                writer(log, cast(BinaryIO, member))


def write_bundle(
    logs: Iterable[RecordedLog],
    sink: BinaryIO,
    *,
    formats: Sequence[str] = tuple(EXPORT_FORMATS),
    selection: Mapping[str, Any] | None = None,
    allow_identified: bool = False,
) -> None:
    """One zip for a study, written to `sink` one session at a time: a folder per session, `index.csv` and
    `index.json` (with `selection`, the criteria the sessions were chosen by, e.g. date range and diagnosis)."""
    for fmt in formats:
        check_format(fmt)
    folders: dict[str, int] = {}
    rows = []
    with open_zip(sink) as archive:
        for index, log in enumerate(logs):
            identifying = identifying_fields(log.metadata.get("patient") or {})
            if identifying and not allow_identified:
                raise SessionLogError(
                    f"logs[{index}].metadata.patient.{identifying[0]}", "<not shown>", "study bundles are pseudonymised"
                )
            folder = session_file_stem(log)
            if folder in folders:
                raise SessionLogError(
                    f"logs[{index}].metadata.session_id", log.session_id, f"duplicate of logs[{folders[folder]}]"
                )
            folders[folder] = index
            write_session_folder(archive, folder, log, formats)
            rows.append(index_row(log, folder))
        archive.writestr("index.csv", _index_csv(rows))
        index_document = {"selection": dict(selection or {}), "formats": list(formats), "sessions": rows}
        archive.writestr("index.json", to_json(index_document, indent=2))


def export_bundle(
    logs: Sequence[RecordedLog],
    *,
    formats: Sequence[str] = tuple(EXPORT_FORMATS),
    selection: Mapping[str, Any] | None = None,
    allow_identified: bool = False,
) -> bytes:
    """`write_bundle` into memory."""
    buffer = io.BytesIO()
    write_bundle(logs, buffer, formats=formats, selection=selection, allow_identified=allow_identified)
    return buffer.getvalue()
