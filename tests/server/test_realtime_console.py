"""Issue 20 defect 8 against a real console (`serve` and its robot daemon as processes): `/health` says how
the worker is scheduled, and a CPU-heavy preview in the web process does not end a running session."""

from __future__ import annotations

import os
from collections.abc import Iterator

import pytest

from benchmarks.fault_harness import SHORT_SINE, Console
from tests.server.conftest import finished_preview

pytestmark = pytest.mark.slow

# In the web process such a preview held the GIL in compiled kernels for seconds at a time (a 590 s one: up
# to 7 s between two 100 ms beats, measured), over the daemon's 1 s tolerance. In its niced process it
# takes many minutes on the loaded 2-core test machine (load average 20), hence the long timeout.
HEAVY_PREVIEW = {"segments": [{"cue": SHORT_SINE, "duration_s": 200.0}]}


@pytest.fixture(scope="module")
def console(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Console]:
    """One console for the module (its tests leave every process of it running), with a CPU-claim directory
    of its own."""
    root = tmp_path_factory.mktemp("realtime")
    instance = Console(root / "console", extra_env={"SSP_REHAB_REALTIME_LOCK_DIR": str(root / "claims")})
    instance.start()
    try:
        yield instance
    finally:
        instance.stop()


def test_health_says_how_the_worker_is_scheduled(console: Console) -> None:
    realtime = console.health()["realtime"]
    assert set(realtime) == {"policy", "priority", "cpu", "granted", "refusals", "how_to_fix"}
    if os.geteuid() == 0:  # root may use SCHED_FIFO; the claim directory is this test's own
        assert realtime["policy"] == "fifo" and realtime["priority"] == 80, realtime
        assert realtime["cpu"] == max(os.sched_getaffinity(0)) and realtime["granted"] is True, realtime
        assert realtime["how_to_fix"] is None
    else:
        assert realtime["granted"] is False and "LimitRTPRIO" in realtime["how_to_fix"], realtime


@pytest.mark.timeout(2400)
def test_a_heavy_preview_during_a_run_does_not_end_it(console: Console) -> None:
    """Before: the preview ran in the web process, its beat to the daemon starved for over 1 s, and the
    daemon ended the run `interrupted` ("console … stopped answering for over 1 s")."""
    session_id = console.book(segments=[{"cue": SHORT_SINE, "duration_s": 600.0}])
    started = console.post(f"/sessions/{session_id}/start")
    assert started.status_code == 200, started.text
    run_id = started.json()["id"]
    console.wait_moving()
    started = console.post("/prescriptions/previews", json=HEAVY_PREVIEW)
    preview = finished_preview(console.get, started, timeout_s=2000.0)
    assert preview["state"] == "ready" and preview["preview"]["verdict"]["accepted"] is True, preview["state"]
    run = console.run(run_id)
    assert run["state"] == "running" and run["outcome"] is None, run
    stops = [e for e in console.events(run_id) if e["kind"] in ("run_ended", "service_lost", "controlled_stop")]
    assert not stops, stops
    assert console.post(f"/sessions/{session_id}/stop").status_code == 200
