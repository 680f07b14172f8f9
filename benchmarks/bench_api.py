"""Console-service benchmarks (issue 15 §4, issue 6).

1. Throughput with 50 concurrent clients (Debian's `wrk`, keep-alive, its own CPU reported) of
   `GET /api/v1/patients?limit=50` and of the clinic-local week (`GET /api/v1/schedule/week`, one robot),
   on SQLite and PostgreSQL, with 1 and 2 web processes (`uvicorn --workers N`, no robot). In the same run,
   on the same seeded database (200 patients, 2,000 bookings) and process count, a bare FastAPI +
   SQLAlchemy app (benchmarks/bare_api.py) runs the same queries with no authentication, audit or
   middleware: the baseline. The product's patient listing includes its audited read (journaled, fsync'd).
   Targets: product >= 0.85 x baseline; 2 processes >= 1.4 x 1.
2. Telemetry WebSocket fan-out: 10 clients on `/sessions/{id}/telemetry` with the real worker (kinematic
   backend, 1 kHz), the frame rate each client receives, and the worker's deadline misses per second
   with no client and with 10 clients (same run, so the comparison is a ratio on one machine).
"""

from __future__ import annotations

import asyncio
import datetime as dt
import os
import re
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from benchmarks.fault_harness import stop_robot_daemon

CLIENTS = 50
PATIENTS = 200
BOOKINGS = 2000
# Issue 15 §4: the product's throughput against a bare FastAPI + SQLAlchemy endpoint doing the same query,
# measured in the same run, and the gain from a second web process.
TARGET_RATIO_TO_BASELINE = 0.85
TARGET_SCALING_2_OVER_1 = 1.4
POSTGRES_URL = os.environ.get("SSP_REHAB_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/test")
SECRET = "benchmark-secret-key-0123456789"


def _seed(url: str) -> None:
    from server.db import Database, create_database_engine, upgrade_database
    from server.patients.models import Patient
    from server.prescriptions.models import Prescription, PrescriptionVersion
    from server.scheduling.models import ScheduledSession
    from server.users.schemas import UserCreate
    from server.users.service import create_user

    engine = create_database_engine(url)
    upgrade_database(engine)
    with Database(engine).session() as session:
        admin = create_user(
            session=session,
            data=UserCreate(username="bench", password="bench-password", role="admin", full_name=""),
            actor_id=None,
        )
        patients = [
            Patient(identifier=f"B-{i:05d}", name=f"Bench Patient {i}", date_of_birth=dt.date(1950 + i % 50, 1, 1),
                    sex="female", height_m=1.7, body_mass_kg=70.0, diagnosis="stroke" if i % 2 else "parkinson")
            for i in range(PATIENTS)
        ]  # fmt: skip
        session.add_all(patients)
        session.flush()
        versions = []
        for patient in patients:
            prescription = Prescription(patient_id=patient.id, name="bench", created_by_id=admin.id)
            version = PrescriptionVersion(version=1, content={"segments": []}, created_by_id=admin.id)
            prescription.versions.append(version)
            session.add(prescription)
            versions.append(version)
        session.flush()
        start = dt.datetime(2031, 1, 6, 8, tzinfo=dt.UTC)
        for index in range(BOOKINGS):
            slot_start = start + dt.timedelta(hours=index // 4)  # four robots in parallel, hourly
            patient_index = index % PATIENTS
            session.add(
                ScheduledSession(
                    patient_id=patients[patient_index].id, prescription_version_id=versions[patient_index].id,
                    robot=f"twin-{index % 4 + 1}", therapist_id=admin.id, start_utc=slot_start,
                    end_utc=slot_start + dt.timedelta(minutes=45), duration_s=2700,
                )
            )  # fmt: skip
        session.commit()
    engine.dispose()


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def wait_healthy(base: str, process: subprocess.Popen[bytes], log_path: Path) -> None:
    """Until `GET /api/v1/health` answers 200; raises if the server exits or takes over 120 s."""
    deadline = time.monotonic() + 120.0
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"the server exited: {log_path.read_text()[-2000:]}")
        try:
            if httpx.get(f"{base}/api/v1/health", timeout=1.0).status_code == 200:
                return
        except httpx.HTTPError:
            pass
        time.sleep(0.2)
    process.kill()
    raise RuntimeError("the server did not come up within 120 s")


def _uvicorn(factory: str, url: str, data_dir: Path, workers: int) -> tuple[subprocess.Popen[bytes], str]:
    """The product or the bare baseline, served the same way: uvicorn, N processes, no access log."""
    port = _free_port()
    environment = {
        **os.environ,
        "SSP_REHAB_DATABASE_URL": url,
        "SSP_REHAB_SECRET_KEY": SECRET,
        "SSP_REHAB_DATA_DIR": str(data_dir),
        "SSP_REHAB_START_WORKER": "false",  # no robot: the web processes alone (the daemon is another issue)
        "SSP_REHAB_VIZ_ENABLED": "false",
        "SSP_REHAB_TIMEZONE": "UTC",
    }
    command = [sys.executable, "-m", "uvicorn", factory, "--factory", "--port", str(port), "--workers", str(workers),
               "--no-access-log", "--log-level", "warning"]  # fmt: skip
    log_path = data_dir / f"{factory.split(':')[0]}-{port}.log"
    log = log_path.open("wb")
    process = subprocess.Popen(command, env=environment, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    wait_healthy(base, process, log_path)
    return process, base


def _stop(process: subprocess.Popen[bytes]) -> None:
    process.terminate()
    try:
        process.wait(timeout=30)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait(timeout=10)


WRK_LATENCY = re.compile(r"^\s*(50|90|99)(?:\.0+)?%\s+([\d.]+)(us|ms|s)\s*$", re.M)
UNIT_MS = {"us": 1e-3, "ms": 1.0, "s": 1e3}


def _wrk(url: str, token: str | None, seconds: float) -> dict[str, Any]:
    """wrk with CLIENTS connections; its own CPU time comes from the kernel's rusage of the process."""
    command = ["wrk", "-t", "2", "-c", str(CLIENTS), "-d", f"{seconds:g}s", "--latency", "--timeout", "10s"]
    if token is not None:
        command += ["-H", f"Authorization: Bearer {token}"]
    process = subprocess.Popen([*command, url], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    started = time.perf_counter()
    assert process.stdout is not None
    output = process.stdout.read().decode()
    _, status, usage = os.wait4(process.pid, 0)
    process.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - started
    if process.returncode != 0:
        raise RuntimeError(f"wrk failed: {output}")
    requests_per_s = float(re.search(r"Requests/sec:\s+([\d.]+)", output).group(1))  # type: ignore[union-attr]
    non_2xx = re.search(r"Non-2xx or 3xx responses:\s+(\d+)", output)
    socket_errors = re.search(r"Socket errors:.*", output)
    latencies = {f"p{q}_ms": round(float(v) * UNIT_MS[u], 2) for q, v, u in WRK_LATENCY.findall(output)}
    return {
        "requests_per_s": requests_per_s,
        **latencies,
        "non_2xx": int(non_2xx.group(1)) if non_2xx else 0,
        "socket_errors": socket_errors.group(0) if socket_errors else None,
        "generator_cpu_percent_of_one_core": round(100.0 * (usage.ru_utime + usage.ru_stime) / wall, 1),
    }


QUERIES = {
    "GET /api/v1/patients?limit=50": "/api/v1/patients?limit=50",
    "GET /api/v1/schedule/week (one robot, 168 bookings)": "/api/v1/schedule/week?day=2031-01-20&robot=twin-2",
}


ROUNDS = 3  # product and baseline alternate, so that a change in the machine's load hits both alike


def _median_round(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    ordered = sorted(rounds, key=lambda figures: figures["requests_per_s"])
    return {**ordered[len(ordered) // 2], "requests_per_s_by_round": [r["requests_per_s"] for r in rounds]}


def _measure(url: str, workers: int, seconds: float) -> dict[str, Any]:
    """Product and bare baseline on the same database and process count, both up, measured in turns
    (product, baseline, product, ...); each figure is the median round."""
    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as directory:
        data_dir = Path(directory)
        _seed(url)  # the same 200 patients and 2,000 bookings for the product and the baseline
        product, base = _uvicorn("server.app:create_app", url, data_dir, workers)
        bare = None
        try:
            bare, bare_base = _uvicorn("benchmarks.bare_api:create_bare_app", url, data_dir, workers)
            login = httpx.post(f"{base}/api/v1/auth/login", json={"username": "bench", "password": "bench-password"})
            token = login.json()["access_token"]
            for name, path in QUERIES.items():
                assert httpx.get(base + path, headers={"Authorization": f"Bearer {token}"}).status_code == 200
                assert httpx.get(bare_base + path).status_code == 200
                product_rounds, bare_rounds = [], []
                for _ in range(ROUNDS):
                    product_rounds.append(_wrk(base + path, token, seconds / ROUNDS))
                    bare_rounds.append(_wrk(bare_base + path, None, seconds / ROUNDS))
                figures[name] = {"product": _median_round(product_rounds), "bare_baseline": _median_round(bare_rounds)}
        finally:
            _stop(product)
            if bare is not None:
                _stop(bare)
        journal_left = sum(1 for _ in (data_dir / "audit-journal").glob("*.jsonl"))
    for name in QUERIES:
        ratio = figures[name]["product"]["requests_per_s"] / figures[name]["bare_baseline"]["requests_per_s"]
        figures[name]["product_over_baseline"] = round(ratio, 3)
        figures[name]["target_ratio"] = TARGET_RATIO_TO_BASELINE
        figures[name]["met"] = ratio >= TARGET_RATIO_TO_BASELINE
    # The product drains its audit journal when it stops: nothing should be left behind.
    figures["audit_journal_files_left_after_stop"] = journal_left
    return figures


def _database_runs(fresh_database: Any, seconds: float) -> dict[str, Any]:
    """1 and 2 web processes, each on a freshly seeded database from `fresh_database()` -> (url, drop)."""
    by_workers: dict[str, Any] = {}
    for workers in (1, 2):
        database = fresh_database()
        if database is None:
            return {"skipped": f"PostgreSQL at {POSTGRES_URL} unreachable"}
        url, drop = database
        try:
            by_workers[f"{workers}_web_process{'es' if workers > 1 else ''}"] = _measure(url, workers, seconds)
        finally:
            drop()
    one, two = by_workers["1_web_process"], by_workers["2_web_processes"]
    for query in QUERIES:
        scaling = two[query]["product"]["requests_per_s"] / one[query]["product"]["requests_per_s"]
        by_workers[f"scaling {query}"] = {
            "two_over_one": round(scaling, 3),
            "target": TARGET_SCALING_2_OVER_1,
            "met": scaling >= TARGET_SCALING_2_OVER_1,
        }
    return by_workers


def _sqlite_database() -> tuple[str, Any]:
    directory = tempfile.TemporaryDirectory()
    return f"sqlite:///{Path(directory.name) / 'bench.sqlite3'}", directory.cleanup


FAN_OUT_CLIENTS = 10
TARGET_FRAME_RATE_HZ = 27.0  # the service sends 30 Hz; allow 10 % for scheduling jitter


def _serve_with_robot(data_dir: Path) -> tuple[subprocess.Popen[bytes], str]:
    port = _free_port()
    environment = {**os.environ, "SSP_REHAB_SECRET_KEY": SECRET, "SSP_REHAB_VIZ_ENABLED": "false"}
    command = [sys.executable, "-m", "server.cli.main", "serve", "--backend", "kinematic", "--port", str(port),
               "--data-dir", str(data_dir)]  # fmt: skip
    log = open(data_dir / "service.log", "wb")  # noqa: SIM115 - closed with the process
    process = subprocess.Popen(command, env=environment, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 180.0
    while time.monotonic() < deadline:
        try:
            health = httpx.get(f"{base}/api/v1/health", timeout=1.0)
            if health.status_code == 200 and health.json()["robot_connected"]:
                return process, base
        except httpx.HTTPError:
            pass
        time.sleep(0.5)
    process.kill()
    raise RuntimeError("the service with a robot did not come up within 180 s")


def _deadline_misses(base: str, headers: dict[str, str]) -> tuple[int, int]:
    state = httpx.get(f"{base}/api/v1/robot/state", headers=headers, timeout=10.0).json()
    return int(state["deadline_misses"]), int(state["tick"])


async def _watch(url: str, token: str, seconds: float) -> int:
    import websockets

    frames = 0
    async with websockets.connect(url, additional_headers={"Authorization": f"Bearer {token}"}) as socket:
        stop_at = time.monotonic() + seconds
        while time.monotonic() < stop_at:
            await asyncio.wait_for(socket.recv(), timeout=5.0)
            frames += 1
    return frames


def _misses_per_s(base: str, headers: dict[str, str], during: Any) -> tuple[float, Any]:
    misses_before, tick_before = _deadline_misses(base, headers)
    started = time.perf_counter()
    result = during()
    elapsed = time.perf_counter() - started
    misses_after, tick_after = _deadline_misses(base, headers)
    return (misses_after - misses_before) / elapsed, (result, tick_after - tick_before)


def _fan_out(seconds: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as directory:
        data_dir = Path(directory)
        _seed(f"sqlite:///{(data_dir / 'ssp-rehab.sqlite3').resolve()}")  # the default database of `serve`
        process, base = _serve_with_robot(data_dir)
        try:
            login = httpx.post(f"{base}/api/v1/auth/login", json={"username": "bench", "password": "bench-password"})
            token = login.json()["access_token"]
            headers = {"Authorization": f"Bearer {token}"}
            url = base.replace("http://", "ws://") + "/api/v1/sessions/1/telemetry"
            idle_misses, (_, idle_ticks) = _misses_per_s(base, headers, lambda: time.sleep(seconds))

            async def watch_all() -> list[int]:
                return list(await asyncio.gather(*(_watch(url, token, seconds) for _ in range(FAN_OUT_CLIENTS))))

            fan_out_misses, (frames, fan_out_ticks) = _misses_per_s(base, headers, lambda: asyncio.run(watch_all()))
        finally:
            process.terminate()
            process.wait(timeout=60)
            stop_robot_daemon(data_dir)
    rates = [count / seconds for count in frames]
    return {
        "clients": FAN_OUT_CLIENTS,
        "seconds_per_phase": seconds,
        "frame_rate_min_hz": round(min(rates), 1),
        "frame_rate_mean_hz": round(float(np.mean(rates)), 1),
        "target_frame_rate_hz": TARGET_FRAME_RATE_HZ,
        "worker_ticks_per_s_without_clients": round(idle_ticks / seconds, 1),
        "worker_ticks_per_s_with_clients": round(fan_out_ticks / seconds, 1),
        "deadline_misses_per_s_without_clients": round(idle_misses, 2),
        "deadline_misses_per_s_with_clients": round(fan_out_misses, 2),
        # Not raising the worker's deadline misses: at most 1 more per second than with no client watching.
        "met": min(rates) >= TARGET_FRAME_RATE_HZ and fan_out_misses <= idle_misses + 1.0,
    }


SESSION_SEGMENT = {
    "cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.3, "frequency_hz": 0.25},
    "duration_s": 300.0,
}
MISSES_UNDER_LOAD_RATIO = 1.5  # issue 15 §4: deadline misses under API load within 1.5 × those without


def _session_under_load(seconds: float) -> dict[str, Any]:
    """A simulated session runs (kinematic backend, 1 kHz); the worker's deadline misses per second are
    measured first without API load, then under wrk's 50 clients on GET /patients, in the same run."""
    with tempfile.TemporaryDirectory() as directory:
        data_dir = Path(directory)
        _seed(f"sqlite:///{(data_dir / 'ssp-rehab.sqlite3').resolve()}")
        process, base = _serve_with_robot(data_dir)
        try:
            login = httpx.post(f"{base}/api/v1/auth/login", json={"username": "bench", "password": "bench-password"})
            token = login.json()["access_token"]
            headers = {"Authorization": f"Bearer {token}"}
            with httpx.Client(base_url=base, headers=headers, timeout=120.0) as api:
                patient_id = api.get("/api/v1/patients", params={"limit": 1}).json()[0]["id"]
                prescription = api.post(
                    "/api/v1/prescriptions",
                    json={"patient_id": patient_id, "name": "bench sway", "segments": [SESSION_SEGMENT]},
                )
                prescription.raise_for_status()
                booking = api.post("/api/v1/sessions", json={
                    "patient_id": patient_id, "prescription_id": prescription.json()["id"], "robot": "twin-1",
                    "start": "2032-01-05T09:00:00+00:00", "duration_s": 1800,
                })  # fmt: skip
                booking.raise_for_status()
                started = api.post(f"/api/v1/sessions/{booking.json()[0]['id']}/start")
                started.raise_for_status()
                time.sleep(3.0)  # past the start ramp
                quiet, _ = _misses_per_s(base, headers, lambda: time.sleep(seconds))
                loaded, (load, _) = _misses_per_s(
                    base, headers, lambda: _wrk(f"{base}/api/v1/patients?limit=50", token, seconds)
                )
                state = api.get("/api/v1/robot/state").json()
        finally:
            process.terminate()
            process.wait(timeout=60)
            stop_robot_daemon(data_dir)
    return {
        "seconds_per_phase": seconds,
        "deadline_misses_per_s_without_api_load": round(quiet, 2),
        "deadline_misses_per_s_under_api_load": round(loaded, 2),
        "api_requests_per_s_during_the_session": load["requests_per_s"],
        "session_state_at_the_end": state.get("state"),
        "target_ratio": MISSES_UNDER_LOAD_RATIO,
        # With no misses at all without load, any miss under load is counted against the target.
        "met": loaded <= MISSES_UNDER_LOAD_RATIO * quiet if quiet > 0 else loaded == 0,
    }


def _postgres_schema_url() -> tuple[str, Any] | None:
    from sqlalchemy import create_engine, text

    admin = create_engine(POSTGRES_URL)
    try:
        with admin.begin() as connection:
            schema = f"ssp_rehab_bench_{uuid.uuid4().hex[:10]}"
            connection.execute(text(f'CREATE SCHEMA "{schema}"'))
    except Exception:
        admin.dispose()
        return None

    def drop() -> None:
        with admin.begin() as connection:
            connection.execute(text(f'DROP SCHEMA "{schema}" CASCADE'))
        admin.dispose()

    separator = "&" if "?" in POSTGRES_URL else "?"
    return f"{POSTGRES_URL}{separator}options=-csearch_path%3D{schema}", drop


def run(*, quick: bool) -> dict[str, Any]:
    seconds = 6.0 if quick else 15.0  # per query and app, in ROUNDS turns
    results: dict[str, Any] = {
        "clients": CLIENTS,
        "patients": PATIENTS,
        "bookings": BOOKINGS,
        "load_generator": "wrk -t2 (Debian), keep-alive connections",
        "seconds_per_measurement": seconds,
        # The machine's load when the run started: the figures are only comparable at a similar load.
        "load_average_1min_at_start": round(os.getloadavg()[0], 2),
    }
    if shutil.which("wrk") is None:
        raise RuntimeError("wrk is not installed: apt-get install -y wrk")
    results["sqlite"] = _database_runs(_sqlite_database, seconds)
    results["postgresql"] = _database_runs(_postgres_schema_url, seconds)
    results["load_average_1min_at_end"] = round(os.getloadavg()[0], 2)
    if not quick:
        try:
            results["telemetry_fan_out"] = _fan_out(10.0)
        except Exception as error:  # the worker is another part of the project: report, do not hide the API figures
            results["telemetry_fan_out"] = f"not measured: {type(error).__name__}: {error}"
    try:
        results["session_under_api_load"] = _session_under_load(5.0 if quick else 15.0)
    except Exception as error:
        results["session_under_api_load"] = f"not measured: {type(error).__name__}: {error}"
    return results
