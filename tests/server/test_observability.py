"""Observability (issue 15 §5): /metrics in Prometheus text format behind its own bearer token, API
latency by route, the robot's tick timing and counters moving during a session, and JSON logs carrying
the request id and the run id."""

from __future__ import annotations

import json
import logging
from collections.abc import Iterator
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families
from pydantic import SecretStr

from server.app import create_app
from server.db import Database
from server.observability.logs import configure_logging
from server.settings import Settings
from tests.server.conftest import TELEMETRY_DTYPE, FakeWorker, Seed, booked_session, wait_until

METRICS_TOKEN = "metrics-token-for-the-tests"
BEARER = {"Authorization": f"Bearer {METRICS_TOKEN}"}


@pytest.fixture
def metered_settings(settings: Settings) -> Settings:
    return settings.model_copy(update={"metrics_token": SecretStr(METRICS_TOKEN)})


@pytest.fixture
def metered_robot_client(
    metered_settings: Settings, database: Database, fake_worker: FakeWorker
) -> Iterator[TestClient]:
    with TestClient(create_app(metered_settings, database=database, worker=fake_worker)) as client:
        yield client


def scrape(client: TestClient) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    response = client.get("/metrics", headers=BEARER)
    assert response.status_code == 200 and response.headers["content-type"].startswith("text/plain")
    return {
        (sample.name, tuple(sorted(sample.labels.items()))): sample.value
        for family in text_string_to_metric_families(response.text)
        for sample in family.samples
    }


def test_metrics_are_closed_without_a_token_and_need_exactly_that_token(
    client: TestClient, settings: Settings, database: Database
) -> None:
    assert client.get("/metrics").status_code == 403  # SSP_REHAB_METRICS_TOKEN unset: closed
    assert client.get("/metrics", headers=BEARER).status_code == 403
    metered = settings.model_copy(update={"metrics_token": SecretStr(METRICS_TOKEN)})
    with TestClient(create_app(metered, database=database, worker=None)) as open_client:
        missing = open_client.get("/metrics")
        assert missing.status_code == 401 and missing.headers["WWW-Authenticate"] == "Bearer"
        assert open_client.get("/metrics", headers={"Authorization": "Bearer wrong"}).status_code == 403
        assert open_client.get("/metrics", headers=BEARER).status_code == 200


def test_api_latency_is_a_histogram_by_route_template(
    metered_settings: Settings, database: Database, seed: Seed
) -> None:
    with TestClient(create_app(metered_settings, database=database, worker=None)) as client:
        for _ in range(3):
            assert client.get("/api/v1/patients", headers=seed.headers()).status_code == 200
        assert client.get("/api/v1/patients/424242", headers=seed.headers()).status_code == 404
        samples = scrape(client)
    count = "ssp_rehab_http_request_duration_seconds_count"
    assert samples[(count, (("method", "GET"), ("route", "/api/v1/patients"), ("status", "200")))] == 3
    # The template, never the id: one series per route, not per patient.
    assert samples[(count, (("method", "GET"), ("route", "/api/v1/patients/{patient_id}"), ("status", "404")))] == 1
    assert not any("424242" in str(labels) for _, labels in samples)


def _push_telemetry(worker: FakeWorker, samples: int, *, deadline_misses: int, limit_hits: int) -> None:
    records = np.zeros(samples, dtype=TELEMETRY_DTYPE)
    records["tick"] = np.arange(worker.tick, worker.tick + samples)
    records["tick_compute_us"] = 60.0
    records["lateness_us"] = np.linspace(5.0, 1500.0, samples)
    records["deadline_misses"] = deadline_misses
    records["limit_hits"] = limit_hits
    with worker._lock:
        worker.tick += samples
        worker._telemetry.append(records)


def test_robot_counters_and_histograms_move_during_a_session(
    metered_robot_client: TestClient, seed: Seed, fake_worker: FakeWorker
) -> None:
    client = metered_robot_client
    before = scrape(client)
    assert before[("ssp_rehab_robot_deadline_misses_total", ())] == 0
    booked = booked_session(client, seed.headers())
    assert client.post(f"/api/v1/sessions/{booked.session_id}/start", headers=seed.headers()).status_code == 200
    _push_telemetry(fake_worker, 500, deadline_misses=3, limit_hits=1)
    fake_worker.telemetry_lost = 7  # type: ignore[attr-defined]  # the ring's overrun count, as WorkerClient has it
    wait_until(lambda: scrape(client)[("ssp_rehab_robot_tick_lateness_seconds_count", ())] >= 500)
    assert scrape(client)[("ssp_rehab_session_run_active", ())] == 1
    _push_telemetry(fake_worker, 500, deadline_misses=5, limit_hits=2)
    fake_worker.emit_event("emergency_stop", source="api")
    fake_worker.emit_event("fault", reason="watchdog")
    wait_until(lambda: scrape(client)[("ssp_rehab_robot_faults_total", ())] == 1)
    after = scrape(client)
    assert after[("ssp_rehab_robot_tick_compute_seconds_count", ())] == 1000
    assert after[("ssp_rehab_robot_tick_compute_seconds_bucket", (("le", "7.5e-05"),))] == 1000  # 60 µs each
    assert after[("ssp_rehab_robot_tick_lateness_seconds_bucket", (("le", "0.001"),))] < 1000  # some > 1 ms
    assert after[("ssp_rehab_robot_deadline_misses_total", ())] == 5
    assert after[("ssp_rehab_robot_limit_hits_total", ())] == 2
    assert after[("ssp_rehab_robot_emergency_stops_total", ())] == 1
    assert after[("ssp_rehab_robot_telemetry_lost_total", ())] == 7
    assert after[("ssp_rehab_robot_state", (("state", "running"),))] == 1
    assert after[("ssp_rehab_robot_state", (("state", "idle"),))] == 0
    assert after[("ssp_rehab_session_run_active", ())] == 0  # the fault ended the run
    assert after[("ssp_rehab_robot_connected", ())] == 1


def test_logs_are_json_lines_with_the_request_id_and_the_run_id(
    client: TestClient, seed: Seed, capsys: pytest.CaptureFixture[str]
) -> None:
    root = logging.getLogger()
    saved = (list(root.handlers), root.level)
    try:
        configure_logging("json")
        # A robot daemon recording run 17, as its status in shared memory says.
        running = SimpleNamespace(active_run_id=17, to_dict=lambda: {"state": "ready", "active_run_id": 17})
        client.app.state.robot = SimpleNamespace(status=lambda: running)  # type: ignore[attr-defined]
        response = client.get("/api/v1/patients", params={"search": "Greta"}, headers=seed.headers())
        given = client.get("/api/v1/health", headers={"X-Request-ID": "from-the-proxy-1"})
        logging.getLogger("server.somewhere").warning("plain %s logger", "stdlib")
        lines = [json.loads(line) for line in capsys.readouterr().err.splitlines() if line.startswith("{")]
    finally:
        root.handlers, root.level = saved
        client.app.state.robot = None  # type: ignore[attr-defined]
    requests = [line for line in lines if line.get("event") == "request"]
    first = next(line for line in requests if line["route"] == "/api/v1/patients")
    assert first["request_id"] == response.headers["x-request-id"] and len(first["request_id"]) == 32
    assert first["run_id"] == 17 and first["status"] == 200 and first["level"] == "info"
    service_lines = [line for line in lines if line.get("logger") != "httpx"]  # httpx: the test's own client
    assert "Greta" not in json.dumps(service_lines)  # no query strings (names) in the service's logs
    assert given.headers["x-request-id"] == "from-the-proxy-1"
    assert any(line.get("request_id") == "from-the-proxy-1" for line in requests)
    stdlib = next(line for line in lines if line.get("event") == "plain stdlib logger")
    assert stdlib["logger"] == "server.somewhere" and stdlib["level"] == "warning"
