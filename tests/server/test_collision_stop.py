"""A collision between the twin's parts is a limit like any other (issue 13 §1): the per-tick check stops
the session (controlled stop, the two parts named), and the offline prescription check refuses it."""

from __future__ import annotations

import numpy as np
import pytest

from core.plan.build import check_prescription
from core.plan.limits import LimitCode
from core.plan.rejection import PrescriptionRejected
from core.robot import TwinRobot, named_twin, symmetric_placements
from core.twin_kernels import VIOLATION_FIELDS, TwinKernels
from server.realtime.pipeline import start_along_checked_approach
from server.realtime.telemetry import StopReason, SupervisorState
from tests.server.test_supervisor import Harness

# Bases staggered by only ±60 mm: clear at neutral (44 mm), but a sway of about 80 mm brings rods 4 (or 3)
# of the two robots together, long before any other limit.
_RIGHT, _LEFT = symmetric_placements(0.5, 0.06, 0.5)
NEAR_MISS = TwinRobot(right=_RIGHT, left=_LEFT)
CLEARANCE_ONLY = np.array([np.inf] * 6 + [0.005])  # the kernel's limits vector: only the clearance margin
SWAY_STEP = {"kind": "step", "axis": "y", "final_m_s2": 1.96, "step_time_s": 0.3}


def test_the_tick_kernel_flags_the_legacy_layouts_rods_colliding_at_neutral() -> None:
    kernels = TwinKernels(named_twin("legacy-interleaved"), 0.001)
    sliders, velocity, acceleration = kernels.neutral_sliders(), np.zeros(12), np.zeros(12)
    violation = np.zeros(VIOLATION_FIELDS)
    limits = CLEARANCE_ONLY
    kernels.command(
        np.zeros(6), sliders.copy(), velocity.copy(), np.full(12, -9.0), np.full(12, 9.0), limits,
        sliders, velocity, acceleration, violation,
    )  # fmt: skip
    assert violation[0] == LimitCode.COLLISION
    assert kernels.collision_pair_name(int(violation[1])) == "right rod 3 – left rod 3"
    assert violation[2] == pytest.approx(-0.04)  # the rods' axes intersect: clearance −2 × 20 mm


def test_the_tick_kernel_and_the_batch_clearance_agree_along_a_sway() -> None:
    kernels = TwinKernels(NEAR_MISS, 0.001)
    from core.clearance import min_clearance

    poses = np.zeros((40, 6))
    poses[:, 1] = np.linspace(0.0, 0.12, 40)
    batch = min_clearance(NEAR_MISS, poses)
    sliders, velocity, acceleration = kernels.neutral_sliders(), np.zeros(12), np.zeros(12)
    for index, pose in enumerate(poses):
        violation = np.zeros(VIOLATION_FIELDS)
        kernels.command(
            pose, sliders.copy(), velocity.copy(), np.full(12, -9.0), np.full(12, 9.0), CLEARANCE_ONLY,
            sliders, velocity, acceleration, violation,
        )  # fmt: skip
        assert (violation[0] == LimitCode.COLLISION) == bool(batch.colliding[index])
        if violation[0] == LimitCode.COLLISION:
            assert violation[2] == pytest.approx(batch.clearance_m[index], abs=1e-12)
            assert kernels.collision_pair_name(int(violation[1])) == batch.closest(index)


def test_a_collision_during_a_session_is_a_controlled_stop_naming_the_parts() -> None:
    harness = Harness(NEAR_MISS)
    harness.load(SWAY_STEP, duration_s=6.0)  # loaded unchecked, on purpose
    start_along_checked_approach(harness.pipeline)
    harness.run(20_000, until=lambda: harness.state is SupervisorState.STOPPED)
    assert harness.state is SupervisorState.STOPPED
    assert harness.pipeline.supervisor.stop_reason is StopReason.LIMIT
    hits = [d for k, d, _ in harness.events if k == "limit_hit"]
    assert hits[0]["limit"] == "collision" and hits[0]["unit"] == "m"
    assert " – " in hits[0]["axis"] and "rod" in hits[0]["axis"]
    # Normal motion keeps the stop margin of clearance, so the controlled stop brakes before the parts meet.
    margin = harness.pipeline.config.clearance_margin_m
    assert hits[0]["value"] < hits[0]["limit_value"] == pytest.approx(NEAR_MISS.parts.clearance_min_m + margin)
    from core.clearance import min_clearance

    assert np.min(min_clearance(NEAR_MISS, np.array(harness.poses)).clearance_m) >= NEAR_MISS.parts.clearance_min_m


def test_the_offline_check_refuses_a_prescription_that_collides_naming_the_parts() -> None:
    with pytest.raises(PrescriptionRejected) as refused:
        check_prescription({"segments": [{"cue": SWAY_STEP, "duration_s": 6.0}]}, NEAR_MISS)
    assert refused.value.limit == "collision"
    assert "collision" in str(refused.value) and "rod" in str(refused.value) and "mm" in str(refused.value)
    assert refused.value.to_dict()["violations_by_reason"]
