"""Audited reads off the request path and never lost (issue 15 §3): a read is journaled (fsync'd) before
it is answered and drained into `audit_log` in the background; a process killed between the read and the
database write loses nothing, because the next process replays the journal; a replay inserts once."""

from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import func, select

from benchmarks.bench_api import wait_healthy
from server.app import create_app
from server.audit.journal import AuditJournal
from server.audit.models import AuditEntry
from server.db import Database
from server.settings import Settings
from tests.e2e.conftest import free_port
from tests.server.conftest import PATIENT, Seed, create_patient

ROOT = Path(__file__).resolve().parents[2]


def audit_rows(database: Database, **where: object) -> list[AuditEntry]:
    with database.session() as session:
        query = select(AuditEntry).order_by(AuditEntry.id)
        for name, value in where.items():
            query = query.where(getattr(AuditEntry, name) == value)
        return list(session.scalars(query))


@pytest.fixture
def slow_drain_client(settings: Settings, database: Database) -> Iterator[TestClient]:
    """The service with a drainer that never runs on its own: what the read path itself wrote shows."""
    slow = settings.model_copy(update={"audit_drain_interval_s": 3600.0})
    with TestClient(create_app(slow, database=database, worker=None)) as client:
        yield client


def test_a_read_is_journaled_on_disk_not_written_in_the_request(
    slow_drain_client: TestClient, database: Database, seed: Seed, settings: Settings
) -> None:
    patient_id = create_patient(slow_drain_client, seed.headers())
    assert slow_drain_client.get(f"/api/v1/patients/{patient_id}", headers=seed.headers()).status_code == 200
    assert audit_rows(database, action="read") == []  # no database write on the read's path
    journal_lines = [
        json.loads(line)
        for path in (settings.data_dir / "audit-journal").glob("*.jsonl")
        for line in path.read_text().splitlines()
    ]
    assert [(e["action"], e["resource_id"], e["user_id"]) for e in journal_lines] == [
        ("read", patient_id, seed.therapist_id)
    ]
    assert PATIENT["name"] not in str(journal_lines)
    # The audit log shows it at once (listing drains first), exactly once.
    entries = slow_drain_client.get(
        "/api/v1/audit", params={"resource_type": "patient"}, headers=seed.headers("admin")
    ).json()
    assert [e["action"] for e in entries] == ["read", "create"]
    assert len(audit_rows(database, action="read")) == 1


def test_a_replayed_journal_inserts_each_entry_once_and_skips_a_torn_line(database: Database, tmp_path: Path) -> None:
    journal = AuditJournal(tmp_path / "journal", drain_interval_s=3600.0)
    journal.open(database)
    try:
        for resource_id in (1, 2):
            journal.append(user_id=None, action="read", resource_type="patient", resource_id=resource_id)
        active = next((tmp_path / "journal").glob("*.active.jsonl"))
        # A copy of the file as if the process had died after the database commit but before removing it,
        # plus a line torn by a crash in the middle of a write.
        leftover = tmp_path / "journal" / "0-crashed.draining.jsonl"
        leftover.write_bytes(active.read_bytes() + b'{"journal_id": "torn", "utc"')
        assert journal.drain() == 2
        assert journal.drain() == 0
    finally:
        journal.close()
    assert sorted(e.resource_id for e in audit_rows(database, action="read")) == [1, 2]
    assert list((tmp_path / "journal").iterdir()) == []


def _serve(data_dir: Path, port: int, **environment: str) -> subprocess.Popen[bytes]:
    env = {
        **os.environ,
        "SSP_REHAB_DATA_DIR": str(data_dir),
        "SSP_REHAB_START_WORKER": "false",
        "SSP_REHAB_VIZ_ENABLED": "false",
        "SSP_REHAB_SECRET_KEY": "journal-test-secret-key-0123456789",
        **environment,
    }
    command = [sys.executable, "-m", "uvicorn", "server.app:create_app", "--factory", "--port", str(port)]
    log_path = data_dir / f"serve-{port}.log"
    process = subprocess.Popen(command, cwd=ROOT, env=env, stdout=log_path.open("wb"), stderr=subprocess.STDOUT)
    wait_healthy(f"http://127.0.0.1:{port}", process, log_path)
    return process


@pytest.mark.slow
def test_a_process_killed_after_answering_a_read_loses_no_audit_record(tmp_path: Path) -> None:
    subprocess.run(
        [sys.executable, "-m", "server.cli.main", "create-user", "--username", "auditor", "--password",
         "auditor-password-1", "--role", "admin", "--data-dir", str(tmp_path)],
        check=True, cwd=ROOT, capture_output=True,
    )  # fmt: skip
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    # The drainer would run only after an hour: the kill lands between the read and the database write.
    first = _serve(tmp_path, port, SSP_REHAB_AUDIT_DRAIN_INTERVAL_S="3600")
    try:
        login = httpx.post(f"{base}/api/v1/auth/login", json={"username": "auditor", "password": "auditor-password-1"})
        headers = {"Authorization": f"Bearer {login.json()['access_token']}"}
        created = httpx.post(f"{base}/api/v1/patients", json=PATIENT, headers=headers)
        patient_id = created.json()["id"]
        assert httpx.get(f"{base}/api/v1/patients/{patient_id}", headers=headers).status_code == 200
    finally:
        first.send_signal(signal.SIGKILL)
        first.wait(30)
    with sqlite3.connect(tmp_path / "ssp-rehab.sqlite3") as database:
        reads = database.execute("SELECT COUNT(*) FROM audit_log WHERE action = 'read'").fetchone()[0]
    assert reads == 0  # the record exists only in the journal now
    second = _serve(tmp_path, port)
    try:
        entries = httpx.get(f"{base}/api/v1/audit", params={"resource_type": "patient"}, headers=headers).json()
        assert [(e["action"], e["resource_id"]) for e in entries] == [("read", patient_id), ("create", patient_id)]
    finally:
        second.terminate()
        second.wait(30)
    assert list((tmp_path / "audit-journal").glob("*.draining.jsonl")) == []


def test_the_journal_drains_in_the_background(client: TestClient, database: Database, seed: Seed) -> None:
    patient_id = create_patient(client, seed.headers())
    client.get(f"/api/v1/patients/{patient_id}", headers=seed.headers())
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        with database.session() as session:
            if session.scalar(select(func.count()).select_from(AuditEntry).where(AuditEntry.action == "read")):
                return
        time.sleep(0.05)
    raise AssertionError("the journaled read never reached the audit log")
