"""The clearance model (core/clearance.py): capsule distances, which pairs it checks, and the layouts."""

from __future__ import annotations

import math

import numpy as np
import pytest

from core.clearance import PartKind, min_clearance, segment_distance, twin_clearance
from core.kinematics import LegViolation, twin_inverse_kinematics
from core.robot import PartDimensions, TwinRobot, load_twin, named_twin, save_twin
from core.workspace import axis_ranges, sample_cloud, stance_reachability


def brute_force_distance(a: np.ndarray, b: np.ndarray, samples: int = 801) -> float:
    """Smallest distance between two segments by dense sampling of both."""
    t = np.linspace(0.0, 1.0, samples)
    points_a = a[0] + t[:, None] * (a[1] - a[0])
    points_b = b[0] + t[:, None] * (b[1] - b[0])
    return float(np.min(np.linalg.norm(points_a[:, None, :] - points_b[None, :, :], axis=-1)))


def test_segment_distance_matches_brute_force_sampling() -> None:
    rng = np.random.default_rng(3)
    for _ in range(200):
        a, b = rng.uniform(-1.0, 1.0, (2, 2, 3))
        exact = segment_distance(a, b)
        sampled = brute_force_distance(a, b)
        # Sampling can only overestimate, by at most half a sample step on each segment.
        step = (np.linalg.norm(a[1] - a[0]) + np.linalg.norm(b[1] - b[0])) / 800
        assert exact <= sampled + 1e-12 and sampled - exact <= step


def test_segment_distance_handles_parallel_crossing_and_degenerate_segments() -> None:
    rail = np.array([[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    assert segment_distance(rail, rail + np.array([0.0, 0.3, 0.0])) == pytest.approx(0.3)  # parallel
    assert segment_distance(rail, np.array([[0.5, -1.0, 0.0], [0.5, 1.0, 0.0]])) == pytest.approx(0.0)  # crossing
    point = np.array([[0.2, 0.0, 0.4], [0.2, 0.0, 0.4]])
    assert segment_distance(rail, point) == pytest.approx(0.4)  # a point
    assert segment_distance(rail, rail + np.array([3.0, 0.0, 0.0])) == pytest.approx(1.0)  # collinear, apart


def test_capsule_clearances_of_the_twin_match_brute_force_sampled_distances() -> None:
    twin = named_twin("legacy-interleaved")
    model = twin_clearance(twin)
    stance = np.random.default_rng(4).uniform(-1.0, 1.0, (3, 6)) * np.array([0.1, 0.05, 0.05, 0.05, 0.05, 0.1])
    segments = model.segments(stance)
    clearances = model.pair_clearances(stance)
    radius = model.table.radius
    rng = np.random.default_rng(5)
    for pose in range(len(stance)):
        for k in rng.choice(len(model.table.pairs), 60, replace=False):
            a, b = model.table.pairs[k]
            sampled = brute_force_distance(segments[pose, a], segments[pose, b]) - radius[a] - radius[b]
            assert clearances[pose, k] == pytest.approx(sampled, abs=5e-3)
            assert clearances[pose, k] <= sampled + 1e-12
    # The pruned minimum is the exact minimum over every pair.
    result = model.clearance(stance)
    np.testing.assert_allclose(result.clearance_m, np.minimum(clearances.min(axis=1), model.platform_clearance_m))


def test_pairs_that_share_a_joint_are_not_checked_and_every_other_kind_is() -> None:
    model = twin_clearance(named_twin("legacy-interleaved"))
    names = set(model.table.pair_names)
    assert "right rod 3 – right slider 3" not in names and "right slider 3 – right rod 3" not in names
    assert not any("right rod 3 – right platform" in n or n.startswith("right platform – right rod") for n in names)
    assert not any("rail" in n.split(" – ")[0] and "rail" in n.split(" – ")[1] for n in names)  # rails are fixed
    kinds = {
        tuple(sorted((PartKind(model.table.kind[a]).name, PartKind(model.table.kind[b]).name)))
        for a, b in model.table.pairs
    }
    assert {("ROD", "ROD"), ("RAIL", "ROD"), ("PLATFORM", "ROD"), ("SLIDER", "SLIDER")} <= kinds
    assert model.platform_pair_name  # platform–platform: checked once, the feet move as one body


def test_the_legacy_layout_reports_rods_3_and_4_of_both_robots_colliding_at_neutral() -> None:
    model = twin_clearance(named_twin("legacy-interleaved"))
    clearances = model.pair_clearances(np.zeros((1, 6)))[0]
    colliding = {model.table.pair_names[k] for k in np.flatnonzero(clearances < 0.0)}
    assert colliding == {"right rod 3 – left rod 3", "right rod 4 – left rod 4"}
    # The rods' axes intersect: the capsules overlap by both radii.
    assert min(clearances) == pytest.approx(-0.04, abs=1e-9)


def test_collision_flags_every_leg_of_both_robots_and_names_the_parts() -> None:
    solutions = twin_inverse_kinematics(named_twin("legacy-interleaved"), np.zeros((2, 6)), check=False)
    for solution in solutions.values():
        assert np.all(solution.violations & LegViolation.COLLISION)
        violation = next(v for v in solution.limit_violations() if "collision" in v.reason)
        assert "right rod 3 – left rod 3" in violation.reason
        assert violation.unit == "m" and violation.value < violation.limit


def test_rod_diameter_is_configurable_and_changes_the_clearance(tmp_path) -> None:  # type: ignore[no-untyped-def]
    twin = named_twin("side-by-side")
    thick = TwinRobot(right=twin.right, left=twin.left, parts=PartDimensions(rod_diameter_m=0.06))
    normal_model, thick_model = twin_clearance(twin), twin_clearance(thick)
    pair = "right rod 2 – right rod 3"
    normal = normal_model.pair_clearances(np.zeros((1, 6)))[0, normal_model.table.pair_names.index(pair)]
    thicker = thick_model.pair_clearances(np.zeros((1, 6)))[0, thick_model.table.pair_names.index(pair)]
    assert thicker == pytest.approx(normal - 0.02)  # both rods 10 mm thicker in radius
    save_twin(thick, tmp_path / "thick.toml")
    assert load_twin(tmp_path / "thick.toml").parts.rod_diameter_m == 0.06


def test_the_default_layout_is_collision_free_over_its_whole_reported_workspace(twin: TwinRobot) -> None:
    """Sample the reported workspace (every axis range and a 6-DOF cloud in the widened box) with the
    clearance alone: nothing that is reported reachable comes closer than the margin."""
    reachability = stance_reachability(twin)
    ranges = axis_ranges(reachability, scan_points=400, bisection_steps=20)
    rays = []
    for axis, r in enumerate(ranges):
        for end in np.linspace(r.minimum, r.maximum, 201):
            pose = np.zeros(6)
            pose[axis] = end
            rays.append(pose)
    cloud = sample_cloud(reachability, ranges, 40_000, seed=7)
    reported = np.concatenate([np.array(rays), cloud.offsets[cloud.reachable]])
    assert len(reported) > 2000
    clearance = min_clearance(twin, reported)
    assert np.min(clearance.clearance_m) >= twin.parts.clearance_min_m, clearance.closest(
        int(np.argmin(clearance.clearance_m))
    )
    # And it is collision-free beyond: the workspace ends at other limits, not at a collision.
    assert all("collision" not in r.limited_by_min + r.limited_by_max for r in ranges)
    assert math.isfinite(float(np.min(clearance.clearance_m)))


@pytest.mark.parametrize("name", ["legacy-interleaved", "side-by-side"])
def test_the_ik_screen_is_exact_wherever_the_clearance_is_near_the_margin(name: str) -> None:
    """The twin IK looks only at pairs a pose-independent bound lets come near, and only below the margin
    plus IK_EXACT_BELOW_M; there it must agree with the exact minimum over every pair."""
    from core.clearance import IK_EXACT_BELOW_M
    from core.kinematics import twin_platform_poses

    twin = named_twin(name)
    model = twin_clearance(twin)
    stance = np.random.default_rng(8).uniform(-1.0, 1.0, (400, 6)) * np.array([0.3, 0.15, 0.1, 0.2, 0.25, 0.3])
    solutions = twin_inverse_kinematics(twin, stance, check=False, clearance_check=False)
    every_rod_reaches = np.all(np.isfinite(np.concatenate([s.slider_positions_m for s in solutions.values()], 1)), 1)
    exact = np.minimum(model.pair_clearances(stance).min(axis=1), model.platform_clearance_m)[every_rod_reaches]
    platform_poses = twin_platform_poses(twin, stance)
    for cutoff in (model.clearance_min_m + 0.02, model.clearance_min_m + IK_EXACT_BELOW_M):
        screened = model.from_solutions(platform_poses, solutions, exact_below_m=cutoff).clearance_m
        screened = screened[every_rod_reaches]
        near = exact < cutoff
        np.testing.assert_allclose(screened[near], exact[near], atol=1e-12)
        assert np.all(screened[~near] <= exact[~near] + 1e-12)  # elsewhere a bound, never more
    assert np.count_nonzero(exact < model.clearance_min_m + IK_EXACT_BELOW_M) > 100
