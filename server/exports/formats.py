"""Session-log exports for fall-detection evaluation: zipped CSV, Parquet, JSON and C3D (issue 6 §5).

Every format carries the same self-describing sidecar (`sidecar(log)`): the log's metadata plus a
`recording` section with the sample count, each field's dtype and shape, each scalar channel's unit,
and the conventions (foot order, frames, COP masking). CSV follows the D-Flow habit of one column per
channel after a time column (REFERENCE.md §5) but keeps events and metadata in their own files instead
of comment lines, so that any CSV reader opens it.
"""

from __future__ import annotations

import csv
import io
import json
import zipfile
from collections.abc import Callable
from typing import Any, BinaryIO

import numpy as np
import pyarrow as pa
import pyarrow.csv as pa_csv
import pyarrow.parquet as pq

from core.plan.limits import LimitCode
from server.exports.c3d import COP_FORCE_THRESHOLD_N, write_c3d
from server.exports.log import RecordedLog, SessionLog, SessionLogError, to_json
from server.hal.base import DriveState
from server.realtime.telemetry import HAL_STATES_BY_CODE, StopReason, SupervisorState

METADATA_KEY = b"ssp_rehab.metadata"
EVENTS_KEY = b"ssp_rehab.events"
EVENT_CSV_HEADER = ("kind", "tick", "tick_time [s]", "utc", "detector", "details")

CONVENTIONS = {
    "feet": "per-foot axes are ordered right, left; sliders right 1-6 then left 1-6 (HAL axis order)",
    "stance_pose": "x, y, z (m), roll, pitch, yaw (rad) of the stance frame relative to neutral; R = Rx*Ry*Rz",
    "plate_cop": "centre of pressure (x, y) in each foot-plate frame, m; origin at the plate centre",
    "plate_force_z": "vertical load on each foot plate, N, positive when loaded",
    "cop_masking": (
        f"CSV, Parquet and JSON keep COP as recorded; C3D marks it invalid (NaN, point residual -1) "
        f"where plate_force_z < {COP_FORCE_THRESHOLD_N} N, because COP is meaningless on an unloaded plate"
    ),
    "json_numbers": "non-finite numbers (NaN, inf) are written as null in JSON",
}

# What the integer codes of the worker's enum fields mean.
CODE_TABLES: dict[str, dict[int, str]] = {
    "state": {int(state): state.label for state in SupervisorState},
    "hal_state": {code: state.value for code, state in HAL_STATES_BY_CODE.items()},
    "stop_reason": {int(reason): reason.name.lower() for reason in StopReason},
    "limit_code": {int(code): code.label for code in LimitCode},
    "drive_state": {int(state): state.name.lower() for state in DriveState},
}


def sidecar(log: RecordedLog) -> dict[str, Any]:
    """The metadata sidecar: the log's metadata plus how the recording is laid out, units per channel."""
    columns = log.head.columns
    fields = {name: {"dtype": str(values.dtype), "shape": list(values.shape[1:])} for name, values in columns.items()}
    recording = {
        "sample_count": log.sample_count,
        "duration_s": log.duration_s,
        "first_tick": log.first_tick,
        "event_count": len(log.events),
        "fields": fields,
        "channels": log.head.channel_units(),
        "codes": {name: table for name, table in CODE_TABLES.items() if name in columns},
        "conventions": CONVENTIONS,
    }
    return {**log.metadata, "recording": recording}


def open_zip(sink: BinaryIO) -> zipfile.ZipFile:
    """A zip for exports: deflate level 1, because level 6 is ~5x slower for ~15 % smaller telemetry. On a
    sink that cannot seek (a pipe, `stream.ForwardSink`) zipfile writes data descriptors, so it streams."""
    return zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1)


def channel_table(log: SessionLog, *, header_units: bool) -> pa.Table:
    """One column per scalar channel; CSV headers carry the unit, Parquet keeps it in field metadata."""
    arrays, schema_fields = [], []
    for channel in log.channels():
        array = pa.array(channel.values)
        name = channel.header if header_units else channel.name
        schema_fields.append(pa.field(name, array.type, metadata={"unit": channel.unit, "field": channel.field}))
        arrays.append(array)
    return pa.Table.from_arrays(arrays, schema=pa.schema(schema_fields))


def events_csv(log: RecordedLog) -> bytes:
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(EVENT_CSV_HEADER)
    for event in log.events:
        writer.writerow(
            (
                event["kind"],
                event["tick"],
                repr(event["tick_time_s"]),
                event["utc"],
                event["detector"] or "",
                to_json(event["details"]),
            )
        )
    return text.getvalue().encode()


def write_csv_members(archive: zipfile.ZipFile, folder: str, log: RecordedLog) -> None:
    """Write `telemetry.csv` (a time column first, one column per channel, `name [unit]` headers),
    `events.csv` and `metadata.json` into `folder` of an open zip, the telemetry batch by batch."""
    with archive.open(f"{folder}telemetry.csv", "w", force_zip64=True) as telemetry:
        writer = None
        for batch in log.batches():
            table = channel_table(batch, header_units=True)
            writer = writer or pa_csv.CSVWriter(telemetry, table.schema)
            writer.write_table(table)
        if writer is not None:
            writer.close()
    archive.writestr(f"{folder}events.csv", events_csv(log))
    archive.writestr(f"{folder}metadata.json", to_json(sidecar(log), indent=2))


def write_csv(log: RecordedLog, sink: BinaryIO) -> None:
    with open_zip(sink) as archive:
        write_csv_members(archive, "", log)


def write_parquet(log: RecordedLog, sink: BinaryIO) -> None:
    """A Parquet table of the channels; units in field metadata, sidecar and events in schema metadata.
    One row group per batch."""
    metadata = {METADATA_KEY: to_json(sidecar(log)).encode(), EVENTS_KEY: to_json(log.events).encode()}
    writer = None
    for batch in log.batches():
        table = channel_table(batch, header_units=False).replace_schema_metadata(metadata)
        writer = writer or pq.ParquetWriter(sink, table.schema)
        writer.write_table(table)
    if writer is not None:
        writer.close()


def _json_column(values: np.ndarray) -> list[Any]:
    if values.dtype.kind in "fc" and not np.all(np.isfinite(values)):
        as_objects = values.astype(object)
        as_objects[~np.isfinite(values)] = None
        return as_objects.tolist()
    return values.tolist()


def write_json(log: RecordedLog, sink: BinaryIO) -> None:
    """One JSON document `{metadata, events, columns}`; columns keep their field names and shapes.

    Written one column and one batch at a time: the Python lists of a whole session at 1 kHz would need
    gigabytes."""
    sink.write(b'{"metadata":' + to_json(sidecar(log)).encode() + b',"events":' + to_json(log.events).encode())
    for index, name in enumerate(log.head.field_order()):
        sink.write((b',"columns":{' if index == 0 else b",") + json.dumps(name).encode() + b":[")
        for number, column in enumerate(log.column_batches(name)):
            values = json.dumps(_json_column(column), allow_nan=False, separators=(",", ":"))
            sink.write((b"," if number else b"") + values[1:-1].encode())
        sink.write(b"]")
    sink.write(b"}}")


def session_log_from_json(data: bytes | str) -> SessionLog:
    """Read back an `export_json` document (nulls in floating-point columns become NaN)."""
    document = json.loads(data)
    metadata = dict(document["metadata"])
    fields = metadata.pop("recording")["fields"]
    columns = {
        name: np.array(values, dtype=float if np.dtype(fields[name]["dtype"]).kind in "fc" else None).astype(
            fields[name]["dtype"]
        )
        for name, values in document["columns"].items()
    }
    return SessionLog(columns=columns, events=document["events"], metadata=metadata)


ExportWriter = Callable[[RecordedLog, BinaryIO], None]
# format -> (writer, media type, file name suffix)
EXPORT_FORMATS: dict[str, tuple[ExportWriter, str, str]] = {
    "csv": (write_csv, "application/zip", "-csv.zip"),
    "parquet": (write_parquet, "application/vnd.apache.parquet", ".parquet"),
    "json": (write_json, "application/json", ".json"),
    "c3d": (write_c3d, "application/octet-stream", ".c3d"),
}


def session_file_stem(log: RecordedLog) -> str:
    """`session-<id>`, with anything but letters, digits, `-`, `_` and `.` replaced, safe as a file name."""
    safe_id = "".join(c if c.isascii() and (c.isalnum() or c in "-_.") else "_" for c in log.session_id)
    return f"session-{safe_id}"


def check_format(fmt: str) -> tuple[ExportWriter, str, str]:
    if fmt not in EXPORT_FORMATS:
        raise SessionLogError("format", fmt, f"one of {', '.join(EXPORT_FORMATS)}")
    return EXPORT_FORMATS[fmt]


def export_session(log: RecordedLog, fmt: str) -> tuple[bytes, str, str]:
    """(file bytes, media type, file name) of one session log in `fmt`: csv | parquet | json | c3d, in
    memory (the service streams with the writers of `EXPORT_FORMATS` instead)."""
    writer, media_type, suffix = check_format(fmt)
    buffer = io.BytesIO()
    writer(log, buffer)
    return buffer.getvalue(), media_type, session_file_stem(log) + suffix
