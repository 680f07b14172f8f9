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

import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from server.exports.bundle import index_row
from server.exports.formats import CODE_TABLES, CONVENTIONS, channel_table
from server.exports.log import SessionLog, to_json
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


def _partition(log: SessionLog) -> tuple[str, str]:
    patient = log.metadata.get("patient") or {}
    pseudonym = patient.get("pseudonym_id")
    started = str(log.metadata.get("started_utc", ""))[:10]
    if not isinstance(pseudonym, str) or not pseudonym or len(started) != 10:
        raise ValueError(f"session {log.session_id}: needs patient.pseudonym_id and started_utc to be partitioned")
    return pseudonym, started


def _events_table(log: SessionLog) -> pa.Table:
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
    schema = pa.schema(
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
    return pa.Table.from_pylist(rows, schema=schema)


def data_dictionary(logs: Sequence[SessionLog]) -> dict[str, Any]:
    """Every column of the three tables: type, unit, the field it comes from and what it means."""
    telemetry: dict[str, dict[str, Any]] = {
        "pseudonym_id": {"type": "string", "unit": "", "partition": True, "description": "pseudonymised patient"},
        "session_date": {"type": "date", "unit": "", "partition": True, "description": "UTC date of the session"},
        "session_id": {"type": "string", "unit": "", "partition": False, "description": "the session run"},
    }
    for log in logs:
        for channel in log.channels():
            if channel.name not in telemetry:
                telemetry[channel.name] = {
                    "type": str(channel.values.dtype),
                    "unit": channel.unit,
                    "field": channel.field,
                    "partition": False,
                    "description": FIELD_DESCRIPTIONS.get(channel.field, FIELD_DESCRIPTIONS.get(channel.name, "")),
                }
    index_columns = sorted({key for log in logs for key in index_row(log, "")} - {"folder"})
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


def write_parquet_dataset(logs: Sequence[SessionLog], root: Path, *, selection: dict[str, Any] | None = None) -> dict:
    """Write `logs` as a hive-partitioned dataset under `root` (new or empty); returns a summary."""
    root = Path(root)
    if root.exists() and any(root.iterdir()):
        raise ValueError(f"dataset directory {root} is not empty: choose a new one")
    for log in logs:
        identifying = identifying_fields(log.metadata.get("patient") or {})
        if identifying or log.metadata.get("patient_identified"):
            raise ValueError(f"session {log.session_id}: the patient is identified ({identifying}); pseudonymise it")
    ids = [log.session_id for log in logs]
    if len(set(ids)) != len(ids):
        raise ValueError("duplicate session ids in the dataset")
    root.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".dataset-", dir=root.parent))
    try:
        samples = 0
        for log in logs:
            pseudonym, day = _partition(log)
            folder = Path(f"pseudonym_id={pseudonym}") / f"session_date={day}"
            table = channel_table(log, header_units=False)
            table = table.append_column("session_id", pa.array([log.session_id] * log.sample_count, pa.string()))
            for name, content in (("telemetry", table), ("events", _events_table(log))):
                (staging / name / folder).mkdir(parents=True, exist_ok=True)
                pq.write_table(content, staging / name / folder / f"{log.session_id}.parquet")
            samples += log.sample_count
        rows = [index_row(log, "") for log in logs]
        for row in rows:
            row.pop("folder")
        pq.write_table(pa.Table.from_pylist(rows), staging / "sessions.parquet")
        dictionary = data_dictionary(logs)
        dictionary["selection"] = selection or {}
        (staging / DATA_DICTIONARY_FILE).write_text(to_json(dictionary, indent=2))
        if root.exists():
            root.rmdir()
        staging.rename(root)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return {"root": str(root), "sessions": len(logs), "samples": samples}


def dataset_zip(logs: Sequence[SessionLog], *, selection: dict[str, Any] | None = None) -> bytes:
    """The dataset as one zip for download (unzip, then point the reader at the folder). Parquet is already
    compressed, so the members are stored."""
    import io
    import zipfile

    with tempfile.TemporaryDirectory(prefix="ssp-rehab-dataset-") as scratch:
        root = Path(scratch) / "dataset"
        write_parquet_dataset(logs, root, selection=selection)
        buffer = io.BytesIO()
        with zipfile.ZipFile(buffer, "w", compression=zipfile.ZIP_STORED) as archive:
            for path in sorted(root.rglob("*")):
                if path.is_file():
                    archive.write(path, path.relative_to(root).as_posix())
        return buffer.getvalue()
