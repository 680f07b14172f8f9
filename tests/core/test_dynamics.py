"""Inverse dynamics (core/dynamics.py): statics, energy balance, twin mapping, per-tick path, refusals."""

from __future__ import annotations

import dataclasses
import tracemalloc

import numpy as np
import pytest

from core.dynamics import (
    DynamicsError,
    InverseDynamics,
    PayloadModel,
    TwinInverseDynamics,
    force_summary,
    paper_step_trajectory,
)
from core.kinematics import (
    euler_rate_matrices,
    inverse_kinematics,
    platform_joints_world,
    pose_jacobian,
    rotation_matrices,
)
from core.physics import GRAVITY_M_S2
from core.robot import DescriptionError, SSPRobot

STILL = np.zeros(6)


def _rod_units(robot: SSPRobot, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit rod directions slider → platform joint (6, 3) and platform-joint levers R·B (6, 3)."""
    sliders = inverse_kinematics(robot, pose).slider_positions_m[0]
    rotation = rotation_matrices(pose[None, 3:])[0]
    joints = platform_joints_world(robot, pose[None, :3], rotation[None])[0]
    anchors = np.stack([sliders, robot.rail_y_m, np.full(6, robot.rail_z_m)], axis=1)
    return (joints - anchors) / robot.rod_length_m, joints - pose[:3]


@pytest.mark.parametrize("pose_offset", [np.zeros(6), np.array([0.05, -0.04, 0.08, 0.1, -0.06, 0.15])])
def test_static_forces_balance_gravity_through_the_rods(robot: SSPRobot, pose_offset: np.ndarray) -> None:
    payload = PayloadModel(80.0, (0.03, -0.02, 0.9), (10.0, 11.0, 1.5))
    pose = np.asarray(robot.neutral_pose) + pose_offset
    forces = InverseDynamics(robot, payload, include_rods=False).slider_forces(pose, STILL, STILL)[0]
    units, levers = _rod_units(robot, pose)
    # A massless rod carries an axial force n along its direction; the drive balances its rail component.
    axial = forces / units[:, 0]
    weight = (robot.mass.platform_mass_kg + payload.mass_kg) * GRAVITY_M_S2
    assert np.sum(axial * units[:, 2]) == pytest.approx(weight, rel=1e-9)
    # The same forces from an independent static solve of the platform's six equilibrium equations.
    rotation = rotation_matrices(pose[None, 3:])[0]
    com = rotation @ np.asarray(payload.com_m) * payload.mass_kg / (payload.mass_kg + robot.mass.platform_mass_kg)
    load = np.array([0.0, 0.0, weight])
    equations = np.vstack([units.T, np.cross(levers, units).T])
    tensions = np.linalg.solve(equations, np.concatenate([load, np.cross(com, load)]))
    np.testing.assert_allclose(forces, tensions * units[:, 0], rtol=1e-9)


def test_rod_mass_is_carried_half_by_the_rails(robot: SSPRobot) -> None:
    """At rest a uniform rod's weight splits between its two ends; the rail takes the slider half."""
    pose = np.asarray(robot.neutral_pose, dtype=float)
    with_rods = InverseDynamics(robot).slider_forces(pose, STILL, STILL)[0]
    units, _ = _rod_units(robot, pose)
    light = dataclasses.replace(robot, mass=dataclasses.replace(robot.mass, rod_mass_kg=0.0))
    base = InverseDynamics(light).slider_forces(pose, STILL, STILL)[0]
    added_vertical = np.sum((with_rods - base) / units[:, 0] * units[:, 2])
    assert added_vertical == pytest.approx(6 * robot.mass.rod_mass_kg * GRAVITY_M_S2 / 2, rel=1e-9)


def test_drive_power_equals_rate_of_change_of_energy(robot: SSPRobot) -> None:
    """Σ F·ẋ = d(kinetic + potential)/dt along a 6-DoF motion: platform, payload, sliders and rods."""
    payload = PayloadModel(70.0, (0.02, 0.01, 0.95), (12.0, 13.0, 1.2))
    dynamics = InverseDynamics(robot, payload)
    times = np.linspace(0.0, 1.0, 8001)
    amplitude = np.array([0.05, 0.04, 0.03, 0.1, 0.08, 0.12])
    omega = np.array([3.0, 4.0, 5.0, 2.5, 3.5, 4.5])
    phase = omega * times[:, None] + np.arange(6)
    poses = np.asarray(robot.neutral_pose) + amplitude * np.sin(phase)
    rates = amplitude * omega * np.cos(phase)
    accelerations = -amplitude * omega**2 * np.sin(phase)
    forces = dynamics.slider_forces(poses, rates, accelerations)
    slider_rates = np.einsum("nij,nj->ni", pose_jacobian(robot, poses), rates)
    power = np.sum(forces * slider_rates, axis=1)

    rotations = rotation_matrices(poses[:, 3:])
    angular = np.einsum("nij,nj->ni", euler_rate_matrices(poses[:, 3:]), rates[:, 3:])
    top = dynamics.arrays.top
    lever = rotations @ top.com_m
    com_velocity = rates[:, :3] + np.cross(angular, lever)
    inertia = rotations @ top.inertia_kg_m2 @ rotations.transpose(0, 2, 1)
    kinetic = 0.5 * top.mass_kg * np.sum(com_velocity**2, 1) + 0.5 * np.einsum(
        "ni,nij,nj->n", angular, inertia, angular
    )
    potential = top.mass_kg * GRAVITY_M_S2 * (poses[:, 2] + lever[:, 2])
    kinetic += 0.5 * robot.mass.slider_mass_kg * np.sum(slider_rates**2, 1)
    joints = platform_joints_world(robot, poses[:, :3], rotations)
    joint_velocity = rates[:, None, :3] + np.cross(angular[:, None, :], joints - poses[:, None, :3])
    slider_velocity = np.zeros_like(joint_velocity)
    slider_velocity[..., 0] = slider_rates
    rod = robot.mass.rod_mass_kg  # uniform rod: T = m/6 (v_A² + v_A·v_P + v_P²)
    kinetic += np.sum(
        rod
        / 6
        * (
            np.sum(slider_velocity**2, -1)
            + np.sum(slider_velocity * joint_velocity, -1)
            + np.sum(joint_velocity**2, -1)
        ),
        axis=1,
    )
    potential += np.sum(rod * GRAVITY_M_S2 * (joints[..., 2] + robot.rail_z_m) / 2, axis=1)
    energy_rate = np.gradient(kinetic + potential, times)
    inner = slice(5, -5)
    assert np.max(np.abs(energy_rate[inner] - power[inner])) < 1e-4 * np.max(np.abs(power))


def test_neglecting_rods_changes_the_forces(robot: SSPRobot) -> None:
    trajectory = paper_step_trajectory("z", 0.2, 0.01)
    poses = trajectory.poses + np.asarray(robot.neutral_pose)
    with_rods = InverseDynamics(robot).slider_forces(poses, trajectory.velocities, trajectory.accelerations)
    without = InverseDynamics(robot, include_rods=False).slider_forces(
        poses, trajectory.velocities, trajectory.accelerations
    )
    assert np.all(np.abs(with_rods) > np.abs(without))


def test_twin_without_payload_is_two_single_robots(twin) -> None:  # type: ignore[no-untyped-def]
    trajectory = paper_step_trajectory("y", 0.2, 0.01)
    forces = TwinInverseDynamics(twin).slider_forces(trajectory.poses, trajectory.velocities, trajectory.accelerations)
    for index, side in enumerate(twin.sides):
        robot = twin.robot_for(side)
        poses = trajectory.poses + np.asarray(robot.neutral_pose)  # default bases: no yaw, stance = platforms
        single = InverseDynamics(robot).slider_forces(poses, trajectory.velocities, trajectory.accelerations)
        np.testing.assert_allclose(forces[:, 6 * index : 6 * index + 6], single, rtol=1e-10, atol=1e-9)


def test_twin_patient_weight_is_shared_by_both_robots(twin) -> None:  # type: ignore[no-untyped-def]
    payload = PayloadModel.from_body(80.0, 1.8)
    loaded = TwinInverseDynamics(twin, payload).step(STILL, STILL, STILL).copy()
    empty = TwinInverseDynamics(twin).step(STILL, STILL, STILL).copy()
    vertical = []
    for index, side in enumerate(twin.sides):
        units, _ = _rod_units(twin.robot_for(side), np.asarray(twin.robot_for(side).neutral_pose, dtype=float))
        extra = loaded[6 * index : 6 * index + 6] - empty[6 * index : 6 * index + 6]
        vertical.append(np.sum(extra / units[:, 0] * units[:, 2]))
    np.testing.assert_allclose(vertical, [40.0 * GRAVITY_M_S2] * 2, rtol=1e-9)


def test_step_matches_batch_and_allocates_nothing(twin) -> None:  # type: ignore[no-untyped-def]
    dynamics = TwinInverseDynamics(twin, PayloadModel.from_body(75.0, 1.75))
    pose = np.array([0.02, -0.03, 0.05, 0.05, -0.04, 0.08])
    rate = np.array([0.1, 0.2, -0.1, 0.3, 0.1, -0.2])
    acceleration = np.array([1.0, -2.0, 3.0, 0.5, -0.4, 0.6])
    batch = dynamics.slider_forces(pose, rate, acceleration)[0]
    first = dynamics.step(pose, rate, acceleration)
    np.testing.assert_allclose(first, batch, rtol=1e-12)
    tracemalloc.start()
    try:
        baseline, _ = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        for _ in range(200):
            result = dynamics.step(pose, rate, acceleration)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert result is first  # the same buffer every tick, not a new array or view
    # What remains is the call's own transient argument handling, bounded and not growing with calls.
    assert peak - baseline < 2048


def test_unreachable_pose_is_refused(robot: SSPRobot) -> None:
    pose = np.asarray(robot.neutral_pose) + np.array([0.0, 0.0, 0.6, 0.0, 0.0, 0.0])
    with pytest.raises(DynamicsError, match="sample 0"):
        InverseDynamics(robot).slider_forces(pose, STILL, STILL)


@pytest.mark.parametrize(
    ("mass_kg", "height_m", "field"),
    [
        (5.0, 1.7, "body_mass_kg"),
        (300.0, 1.7, "body_mass_kg"),
        (70.0, 3.0, "height_m"),
        (float("nan"), 1.7, "body_mass_kg"),
    ],
)
def test_payload_from_body_refuses_out_of_range(mass_kg: float, height_m: float, field: str) -> None:
    with pytest.raises(DescriptionError) as error:
        PayloadModel.from_body(mass_kg, height_m)
    assert error.value.field == field


def test_payload_above_rated_load_is_refused(robot: SSPRobot) -> None:
    with pytest.raises(DescriptionError, match="rated load"):
        InverseDynamics(robot, PayloadModel(robot.mass.rated_payload_kg + 1.0))


def test_paper_trajectory_integrates_the_acceleration_step() -> None:
    trajectory = paper_step_trajectory("z", 0.3, 0.001)
    assert trajectory.accelerations[99, 2] == 5.0 and trajectory.accelerations[100, 2] == 0.5
    assert trajectory.velocities[100, 2] == pytest.approx(0.5)
    assert trajectory.poses[-1, 2] == pytest.approx(0.025 + 0.5 * 0.2 + 0.25 * 0.04)
    np.testing.assert_allclose(
        np.gradient(trajectory.poses[:, 2], trajectory.times_s)[1:-1], trajectory.velocities[1:-1, 2], atol=3e-3
    )


def test_force_summary_band_is_judged_on_each_joints_peak() -> None:
    # Two joints over three samples: peaks 600 N and 2900 N are in the band even though the force passes 0 N.
    in_band = force_summary(np.array([[0.0, -100.0], [600.0, -2900.0], [300.0, 10.0]]))
    assert in_band["in_paper_band"]
    assert in_band["min_abs_force_n"] == 600.0 and in_band["max_abs_force_n"] == 2900.0
    assert in_band["min_instantaneous_abs_force_n"] == 0.0
    assert not force_summary(np.array([[400.0, -2900.0]]))["in_paper_band"]  # a joint that never needs 500 N
    assert not force_summary(np.array([[600.0, 3100.0]]))["in_paper_band"]  # a joint beyond 3000 N
