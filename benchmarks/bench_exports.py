"""Exports of a large run (issue 20 defect 10, Build 7): time to first byte and peak memory, the old path
(the whole file built in memory, as the web process did) against the new one (an export process that
streams batch by batch, `server.exports.jobs`), in the same run, with CPU time beside wall time.

Both paths run in a process of their own started the same way (a forkserver child), so their peak RSS
(`ru_maxrss`) compares: the old one builds the file with `export_session` from the whole log, the new one is
an `ExportJob` fed the run's telemetry as stored chunks (1000 samples each, like the recorder's). Targets:
the new path's first byte within 2 s and its peak RSS under 400 MB whatever the run's length; the old
path's first byte comes only when the whole file is built.
"""

from __future__ import annotations

import datetime as dt
import io
import json
import multiprocessing
import os
import resource
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from core.robot import default_twin
from server.exports import SessionLog, export_session, session_metadata
from server.exports.jobs import ExportJob, ExportJobs
from server.realtime.telemetry import TELEMETRY_DTYPE

FIRST_BYTE_TARGET_S = 2.0
PEAK_RSS_TARGET_MB = 400.0
CHUNK_SAMPLES = 1000
FORMATS = ("csv", "json", "parquet")
PATIENT = {
    "identifier": "BENCH-1",
    "name": "Bench Patient",
    "date_of_birth": "1950-01-01",
    "sex": "female",
    "height_m": 1.65,
    "body_mass_kg": 60.0,
    "affected_side": "left",
}


def _records(sample_count: int) -> np.ndarray:
    rng = np.random.default_rng(1)
    records = np.zeros(sample_count, TELEMETRY_DTYPE)
    records["tick"] = np.arange(sample_count)
    records["time_s"] = np.arange(sample_count) / 1000.0 + rng.uniform(0, 2e-4, sample_count)
    records["utc_s"] = 1.78e9 + records["time_s"]
    for name in ("slider_position_m", "drive_force_n", "stance_pose", "plate_cop_m", "cue_specific_force_m_s2"):
        records[name] = rng.normal(0.0, 0.01, records[name].shape)
    records["plate_force_z_n"] = 320.0 + rng.normal(0.0, 5.0, records["plate_force_z_n"].shape)
    records["lateness_us"] = rng.exponential(60.0, sample_count)
    return records


def _metadata() -> dict[str, Any]:
    return session_metadata(
        session_id="bench-1",
        started_utc=dt.datetime(2026, 12, 1, 9, tzinfo=dt.UTC),
        sample_rate_hz=1000.0,
        patient=PATIENT,
        prescription={"segments": [{"duration_s": 60.0}]},
        prescription_version=1,
        twin=default_twin(),
        salt="bench salt of sixteen bytes",
    )


def _old_path(records_path: str, fmt: str, answer: Any) -> None:
    """The web process's old way: the whole log in memory, the whole file built, then its first byte."""
    start_wall, start_cpu = time.perf_counter(), time.process_time()
    records = np.load(records_path)
    log = SessionLog.from_telemetry(records, [], _metadata())
    body, _, _ = export_session(log, fmt)
    wall = time.perf_counter() - start_wall
    usage = resource.getrusage(resource.RUSAGE_SELF)
    answer.send({"first_byte_s": wall, "total_s": wall, "cpu_s": time.process_time() - start_cpu,
                 "peak_rss_mb": usage.ru_maxrss / 1024, "bytes": len(body)})  # fmt: skip


def _measure_old(records_path: Path, fmt: str) -> dict[str, Any]:
    context = multiprocessing.get_context("forkserver")
    receiver, sender = context.Pipe(duplex=False)
    process = context.Process(target=_old_path, args=(str(records_path), fmt, sender), name="bench-old-export")
    process.start()
    sender.close()
    figures: dict[str, Any] = receiver.recv()
    process.join()
    return figures


def _measure_new(jobs: ExportJobs, records: np.ndarray, fmt: str) -> dict[str, Any]:
    metadata = _metadata()

    def feed(send: Any) -> None:
        send(b"R", json.dumps({"metadata": metadata, "events": []}).encode())
        for start in range(0, len(records), CHUNK_SAMPLES):
            chunk = io.BytesIO()
            np.save(chunk, records[start : start + CHUNK_SAMPLES])
            send(b"C", chunk.getvalue())
        send(b"E", b"")

    started = time.perf_counter()
    job = ExportJob(owner_id=1, spec={"kind": "session", "format": fmt}, feed=feed, filename="bench",
                    media_type="application/octet-stream", total_samples=len(records), description="bench")  # fmt: skip
    jobs.submit(job)
    first_byte_s = None
    while not job.finished():
        if first_byte_s is None and job.output.exists() and job.output.stat().st_size > 0:
            first_byte_s = time.perf_counter() - started
        time.sleep(0.01)
    total_s = time.perf_counter() - started
    status, progress = job.status(), job.progress()
    if status["state"] != "done":
        raise RuntimeError(f"the export failed: {status['error']}")
    first = first_byte_s if first_byte_s is not None else total_s
    return {"first_byte_s": first, "total_s": total_s, "cpu_s": progress["cpu_s"],
            "peak_rss_mb": progress["peak_rss_kb"] / 1024, "bytes": status["bytes"]}  # fmt: skip


def run(*, quick: bool) -> dict[str, Any]:
    sample_count = 30_000 if quick else 300_000
    records = _records(sample_count)
    figures: dict[str, Any] = {"samples": sample_count, "run_minutes_at_1khz": sample_count / 60_000}
    with tempfile.TemporaryDirectory(prefix="ssp-rehab-bench-exports-") as scratch:
        records_path = Path(scratch) / "records.npy"
        np.save(records_path, records)
        jobs = ExportJobs(Path(scratch) / "jobs", max_running=1)
        try:
            for fmt in FORMATS:
                old, new = _measure_old(records_path, fmt), _measure_new(jobs, records, fmt)
                figures[fmt] = {
                    "old_in_memory": {key: round(value, 3) for key, value in old.items()},
                    "new_streamed": {key: round(value, 3) for key, value in new.items()},
                }
        finally:
            jobs.close()
    new_first = max(figures[fmt]["new_streamed"]["first_byte_s"] for fmt in FORMATS)
    new_peak = max(figures[fmt]["new_streamed"]["peak_rss_mb"] for fmt in FORMATS)
    figures["targets"] = {
        "first_byte_s": {"target": FIRST_BYTE_TARGET_S, "worst": new_first, "met": new_first <= FIRST_BYTE_TARGET_S},
        "peak_rss_mb": {"target": PEAK_RSS_TARGET_MB, "worst": new_peak, "met": new_peak <= PEAK_RSS_TARGET_MB},
    }
    figures["load_average_1min"] = round(os.getloadavg()[0], 1)
    return figures
