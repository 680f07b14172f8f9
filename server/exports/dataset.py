"""A study as a hive-partitioned Parquet dataset (issue 16 §9): DuckDB, Dask, Spark or pyarrow read it as it is.

```
<root>/telemetry/pseudonym_id=P-…/session_date=YYYY-MM-DD/<session_id>.parquet   one row per sample
<root>/events/pseudonym_id=P-…/session_date=YYYY-MM-DD/<session_id>.parquet      one row per event
<root>/sessions.parquet                                                            one row per session
<root>/data_dictionary.json                                                        every column: type, unit, meaning
```

Telemetry columns are the scalar channels of the single-session Parquet export (names without units, the
unit in each field's metadata and in the dictionary), plus `session_id`; the partition columns come from
the directory names. Only pseudonymised logs are accepted: the directory names carry the pseudonym.
The dataset is written to a temporary directory beside `root` and renamed into place, so a refusal or a
failure leaves nothing half-written.
"""

from __future__ import annotations

import io
import shutil
import tempfile
import zipfile
from collections.abc import Callable, Iterable, Sequence
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any, BinaryIO, cast

import pyarrow as pa
import pyarrow.parquet as pq

from server.exports.bundle import index_row
from server.exports.formats import CODE_TABLES, CONVENTIONS, channel_table
from server.exports.log import RecordedLog, to_json
from server.exports.metadata import identifying_fields

DATA_DICTIONARY_FILE = "data_dictionary.json"
PARTITIONS = ("pseudonym_id", "session_date")

# What the columns mean; a channel's unit comes from its field's suffix, its meaning from its field here.
FIELD_DESCRIPTIONS = {
    "time_s": "monotonic time of the sample (the tick's start) since the worker started",
    "session_time": "time into the session on the session clock (events' session_time_s use the same clock)",
    "session_time_s": "time into the session on the session clock (events' session_time_s use the same clock)",
    "skipped_ticks": "control periods the loop skipped just before this sample: 0 on time, > 0 a gap",
    "tick_gap": "control periods missing just before this sample (skipped deadlines + lost samples): 0 on time",
    "late": "1 where the tick started more than 500 us after its deadline (the worker's threshold)",
    "tick": "control tick counter of the worker (skipped periods are not counted)",
    "utc_s": "wall clock, POSIX seconds",
    "plate_force_z_n": "vertical load on each foot plate (right, left)",
    "plate_cop_m": "centre of pressure in each foot-plate frame (right, left; x anterior, y left)",
    "harness_load_n": "harness load-cell force",
    "stance_pose": "commanded stance pose relative to neutral (x, y, z m; roll, pitch, yaw rad)",
    "slider_position_m": "measured slider positions, right 1-6 then left 1-6",
    "drive_force_n": "measured drive forces, right 1-6 then left 1-6",
    "cue_specific_force_m_s2": "specific force of the motion cue before washout",
    "cue_angular_velocity_rad_s": "angular velocity of the motion cue before washout",
    "state": "supervisor state (code table in the dictionary's `codes`)",
    "stop_reason": "reason of the latest stop (code table in `codes`)",
}
EVENT_COLUMNS = {
    "session_id": ("string", "", "the session run"),
    "kind": ("string", "", "event kind: fall, state, controlled_stop, limit_hit, ..."),
    "tick": ("int64", "", "worker tick of the event"),
    "tick_time_s": ("float64", "s", "worker clock of the event (same clock as telemetry time)"),
    "session_time_s": ("float64", "s", "time into the session (null outside a session)"),
    "utc": ("string", "", "wall clock, ISO 8601"),
    "detector": ("string", "", "fall detector that fired (fall events)"),
    "details": ("JSON text", "", "the event's details as recorded"),
}


def _partition(log: RecordedLog) -> tuple[str, str]:
    patient = log.metadata.get("patient") or {}
    pseudonym = patient.get("pseudonym_id")
    started = str(log.metadata.get("started_utc", ""))[:10]
    if not isinstance(pseudonym, str) or not pseudonym or len(started) != 10:
        raise ValueError(f"session {log.session_id}: needs patient.pseudonym_id and started_utc to be partitioned")
    return pseudonym, started


EVENTS_SCHEMA = pa.schema(
    [
        ("session_id", pa.string()),
        ("kind", pa.string()),
        ("tick", pa.int64()),
        ("tick_time_s", pa.float64()),
        ("session_time_s", pa.float64()),
        ("utc", pa.string()),
        ("detector", pa.string()),
        ("details", pa.string()),
    ]
)


def _events_table(log: RecordedLog) -> pa.Table:
    rows = [
        {
            "session_id": log.session_id,
            "kind": event["kind"],
            "tick": event["tick"],
            "tick_time_s": event["tick_time_s"],
            "session_time_s": (event.get("details") or {}).get("session_time_s"),
            "utc": event["utc"],
            "detector": event.get("detector"),
            "details": to_json(event.get("details") or {}),
        }
        for event in log.events
    ]
    return pa.Table.from_pylist(rows, schema=EVENTS_SCHEMA)


def _telemetry_columns(log: RecordedLog) -> dict[str, dict[str, Any]]:
    return {
        channel.name: {
            "type": str(channel.values.dtype),
            "unit": channel.unit,
            "field": channel.field,
            "partition": False,
            "description": FIELD_DESCRIPTIONS.get(channel.field, FIELD_DESCRIPTIONS.get(channel.name, "")),
        }
        for channel in log.head.channels()
    }


def data_dictionary(telemetry_columns: dict[str, dict[str, Any]], index_columns: Sequence[str]) -> dict[str, Any]:
    """Every column of the three tables: type, unit, the field it comes from and what it means."""
    telemetry: dict[str, dict[str, Any]] = {
        "pseudonym_id": {"type": "string", "unit": "", "partition": True, "description": "pseudonymised patient"},
        "session_date": {"type": "date", "unit": "", "partition": True, "description": "UTC date of the session"},
        "session_id": {"type": "string", "unit": "", "partition": False, "description": "the session run"},
        **telemetry_columns,
    }
    return {
        "layout": "hive-partitioned Parquet: telemetry/ and events/ by pseudonym_id and session_date",
        "read_with": {
            "duckdb": "select * from read_parquet('telemetry/**/*.parquet', hive_partitioning = true)",
            "pyarrow": "pyarrow.dataset.dataset('telemetry', format='parquet', partitioning='hive')",
        },
        "tables": {
            "telemetry": {"columns": telemetry},
            "events": {
                "columns": {
                    name: {"type": kind, "unit": unit, "description": text}
                    for name, (kind, unit, text) in EVENT_COLUMNS.items()
                }
            },
            "sessions": {
                "columns": {name: {"description": "see docs/exports.md (study index)"} for name in index_columns}
            },
        },
        "codes": CODE_TABLES,
        "conventions": CONVENTIONS,
    }


MemberOpener = Callable[[str], AbstractContextManager[BinaryIO]]


def write_dataset(
    logs: Iterable[RecordedLog], open_member: MemberOpener, *, selection: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Write the dataset's files through `open_member(relative path)`, one session and one batch at a time;
    returns a summary. Refuses an identified patient or a duplicate session id."""
    seen: set[str] = set()
    telemetry_columns: dict[str, dict[str, Any]] = {}
    rows = []
    samples = 0
    for log in logs:
        identifying = identifying_fields(log.metadata.get("patient") or {})
        if identifying or log.metadata.get("patient_identified"):
            raise ValueError(f"session {log.session_id}: the patient is identified ({identifying}); pseudonymise it")
        if log.session_id in seen:
            raise ValueError("duplicate session ids in the dataset")
        seen.add(log.session_id)
        pseudonym, day = _partition(log)
        folder = f"pseudonym_id={pseudonym}/session_date={day}"
        with open_member(f"telemetry/{folder}/{log.session_id}.parquet") as sink:
            writer = None
            for batch in log.batches():
                table = channel_table(batch, header_units=False)
                table = table.append_column("session_id", pa.array([log.session_id] * batch.sample_count, pa.string()))
                writer = writer or pq.ParquetWriter(sink, table.schema)
                writer.write_table(table)
            if writer is not None:
                writer.close()
        with open_member(f"events/{folder}/{log.session_id}.parquet") as sink:
            pq.write_table(_events_table(log), sink)
        telemetry_columns = {**_telemetry_columns(log), **telemetry_columns}
        row = index_row(log, "")
        row.pop("folder")
        rows.append(row)
        samples += log.sample_count
    with open_member("sessions.parquet") as sink:
        pq.write_table(pa.Table.from_pylist(rows), sink)
    dictionary = data_dictionary(telemetry_columns, sorted({key for row in rows for key in row}))
    dictionary["selection"] = selection or {}
    with open_member(DATA_DICTIONARY_FILE) as sink:
        sink.write(to_json(dictionary, indent=2).encode())
    return {"sessions": len(rows), "samples": samples}


def write_parquet_dataset(logs: Sequence[RecordedLog], root: Path, *, selection: dict[str, Any] | None = None) -> dict:
    """Write `logs` as a hive-partitioned dataset under `root` (new or empty); returns a summary."""
    root = Path(root)
    if root.exists() and any(root.iterdir()):
        raise ValueError(f"dataset directory {root} is not empty: choose a new one")
    root.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".dataset-", dir=root.parent))

    def open_file(relative: str) -> BinaryIO:
        path = staging / relative
        path.parent.mkdir(parents=True, exist_ok=True)
        return path.open("wb")

    try:
        summary = write_dataset(logs, open_file, selection=selection)
        if root.exists():
            root.rmdir()
        staging.rename(root)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return {"root": str(root), **summary}


def write_dataset_zip(logs: Iterable[RecordedLog], sink: BinaryIO, *, selection: dict[str, Any] | None = None) -> None:
    """The dataset as one zip for download (unzip, then point the reader at the folder), streamed to `sink`.
    Parquet is already compressed, so the members are stored."""
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_STORED) as archive:

        def open_member(relative: str) -> BinaryIO:
            return cast(BinaryIO, archive.open(relative, "w", force_zip64=True))

        write_dataset(logs, open_member, selection=selection)


def dataset_zip(logs: Sequence[RecordedLog], *, selection: dict[str, Any] | None = None) -> bytes:
    """`write_dataset_zip` into memory."""
    buffer = io.BytesIO()
    write_dataset_zip(logs, buffer, selection=selection)
    return buffer.getvalue()
