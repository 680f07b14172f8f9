"""Issue 20 defect 8: real-time workers beside other software. Each robot's worker gets a CPU of its own
(a machine-wide claim), what the OS refused is said, and the rest of the product yields."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from server.realtime.client import WorkerClient
from server.realtime.loop import configure_realtime
from server.realtime.scheduling import (
    LOCK_DIR_ENVIRONMENT,
    RealtimeReport,
    claim_cpu,
    lower_priority,
    parse_cpu_request,
)

TOLERANT_DRIVES = {"communication_timeout_s": 1.0}
ALLOWED = sorted(os.sched_getaffinity(0), reverse=True)


@pytest.fixture(autouse=True)
def private_claims(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Claims in this test's own directory: the shared machine's other workers do not take part."""
    directory = tmp_path / "claims"
    monkeypatch.setenv(LOCK_DIR_ENVIRONMENT, str(directory))
    return directory


@pytest.mark.skipif(len(ALLOWED) < 2, reason="needs two CPUs allowed to the test")
@pytest.mark.slow
def test_two_workers_on_one_computer_run_on_different_cpus() -> None:
    """Before: both pinned themselves to the last CPU (four installations all sat on CPU 1)."""
    with (
        WorkerClient(None, "kinematic", hal_options=TOLERANT_DRIVES) as first,
        WorkerClient(None, "kinematic", hal_options=TOLERANT_DRIVES) as second,
    ):
        cpus = [os.sched_getaffinity(client.worker_pid) for client in (first, second)]
        assert cpus[0] == {ALLOWED[0]} and cpus[1] == {ALLOWED[1]}, cpus
        assert first.realtime_setup["cpu"] == ALLOWED[0] and second.realtime_setup["cpu"] == ALLOWED[1]


def test_claims_go_highest_first_and_say_plainly_when_none_is_free(private_claims: Path) -> None:
    claims = [claim_cpu("auto", private_claims) for _ in ALLOWED]
    try:
        assert [claim.cpu for claim in claims] == ALLOWED
        left_over = claim_cpu("auto", private_claims)
        assert left_over.cpu is None and left_over.refusal is not None
        assert (
            "claimed by another real-time worker" in left_over.refusal and "SSP_REHAB_REALTIME_CPU" in left_over.refusal
        )
        claims[0].release()  # a worker that ends (however: the kernel drops the flock) frees its CPU
        again = claim_cpu("auto", private_claims)
        assert again.cpu == ALLOWED[0]
        again.release()
    finally:
        for claim in claims:
            claim.release()


def test_a_configured_cpu_is_claimed_and_a_bad_one_is_refused_by_name(private_claims: Path) -> None:
    claim = claim_cpu(ALLOWED[-1], private_claims)
    assert claim.cpu == ALLOWED[-1]
    taken = claim_cpu(str(ALLOWED[-1]), private_claims)
    assert taken.cpu is None and f"CPU {ALLOWED[-1]} is claimed" in (taken.refusal or "")
    claim.release()
    assert claim_cpu("none", private_claims).cpu is None
    with pytest.raises(ValueError, match="realtime_cpu = 'fast'"):
        parse_cpu_request("fast")
    outside = claim_cpu(max(ALLOWED) + 64, private_claims)
    assert outside.cpu is None and "not among the CPUs allowed" in (outside.refusal or "")


def test_a_refused_fifo_priority_is_reported_with_what_to_configure(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    affinity = os.sched_getaffinity(0)
    setup = configure_realtime("auto", 80)
    try:
        assert setup.fifo_priority is None and any("SCHED_FIFO priority 80 refused" in r for r in setup.refusals)
        report = RealtimeReport.from_setup(setup.to_dict()).to_dict()
        assert report["granted"] is False and report["policy"] == "other"
        assert "LimitRTPRIO" in report["how_to_fix"] and "CAP_SYS_NICE" in report["how_to_fix"]
        assert "chrt" in report["how_to_fix"]
    finally:
        setup.release()
        os.sched_setaffinity(0, affinity)


def test_granted_setup_needs_no_fix() -> None:
    report = RealtimeReport.from_setup({"cpu": 1, "fifo_priority": 80, "refusals": []}).to_dict()
    assert report == {
        "policy": "fifo",
        "priority": 80,
        "cpu": 1,
        "granted": True,
        "refusals": [],
        "how_to_fix": None,
    }


def test_lower_priority_only_ever_lowers() -> None:
    import threading

    seen: list[int] = []

    def in_a_thread() -> None:  # the nice value is per thread on Linux: the test's own stays as it was
        lower_priority("a test thread", 7)
        lower_priority("a test thread", 3)
        seen.append(os.getpriority(os.PRIO_PROCESS, 0))

    thread = threading.Thread(target=in_a_thread)
    thread.start()
    thread.join()
    assert seen == [max(7, os.getpriority(os.PRIO_PROCESS, 0))]
