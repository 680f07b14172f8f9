"""The compiled MuJoCo twin: addresses of every joint and sensor, kinematic state from a stance trajectory,
MuJoCo's own inverse dynamics of the closed chains, and the force-plate / harness readings.

Inverse dynamics in MuJoCo (the cross-check of `core.dynamics`): for a state (q, q̇, q̈) that satisfies the
loop constraints at position, velocity and acceleration level, `mj_inverse` with constraints disabled gives
the generalised force τ = M·q̈ + c(q, q̇) − g(q) over all 60 DoF. The real machine supplies it with the twelve
slider forces and the loop reaction forces λ, so  Sᵀ·F + J_loopᵀ·λ = τ  is solved for (F, λ) in least squares
with the loop Jacobians from `mj_jacSite`. Constraint softness plays no part; the residual is reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np

from core.dynamics import LegMotion, PlatformMotion, StanceTrajectory, TwinInverseDynamics
from core.robot import TwinRobot
from server.hal.sim.mjcf import SimModelOptions, neutral_rod_vectors, twin_mjcf


@dataclass(frozen=True)
class InverseResult:
    slider_forces_n: np.ndarray  # (N, 12)
    max_residual: float  # largest |Sᵀ·F + Jᵀ·λ − τ| relative to |τ|


def rms_relative_error(estimate: np.ndarray, reference: np.ndarray) -> float:
    """‖estimate − reference‖_rms / ‖reference‖_rms over all samples and axes."""
    return float(np.sqrt(np.mean((estimate - reference) ** 2)) / np.sqrt(np.mean(reference**2)))


class TwinSimModel:
    """The MuJoCo model of `twin` with index arrays for the twelve slider axes (right 1–6, left 1–6)."""

    def __init__(self, twin: TwinRobot, options: SimModelOptions | None = None) -> None:
        self.twin = twin
        self.options = options or SimModelOptions()
        self.xml = twin_mjcf(twin, self.options)
        self.model = mujoco.MjModel.from_xml_string(self.xml)
        model = self.model
        sides = twin.sides
        self.slider_qpos = np.array([model.joint(f"{s}_slider{i}").qposadr[0] for s in sides for i in range(1, 7)])
        self.slider_dof = np.array([model.joint(f"{s}_slider{i}").dofadr[0] for s in sides for i in range(1, 7)])
        self.rod_qpos = np.array([model.joint(f"{s}_rod{i}").qposadr[0] for s in sides for i in range(1, 7)])
        self.rod_dof = np.array([model.joint(f"{s}_rod{i}").dofadr[0] for s in sides for i in range(1, 7)])
        self.platform_qpos = np.array([model.joint(f"{s}_platform").qposadr[0] for s in sides])
        self.platform_dof = np.array([model.joint(f"{s}_platform").dofadr[0] for s in sides])
        self.platform_body = np.array([model.body(f"{s}_platform").id for s in sides])
        self.plate_site = np.array([model.site(f"{s}_plate").id for s in sides])
        self.loop_sites = [
            (model.site(f"{s}_rod{i}_end").id, model.site(f"{s}_platform_joint{i}").id)
            for s in sides
            for i in range(1, 7)
        ]
        self._plate_force_adr = np.array([model.sensor(f"{s}_plate_force").adr[0] for s in sides])
        self._plate_torque_adr = np.array([model.sensor(f"{s}_plate_torque").adr[0] for s in sides])
        self.has_harness = model.ntendon > 0
        self._harness_adr = model.sensor("harness_length").adr[0] if self.has_harness else -1
        self._neutral_rods = [neutral_rod_vectors(twin.robot_for(s))[1] for s in sides]
        self._base_yaws = [twin.placement(s).base_yaw_rad for s in sides]

    def make_data(self) -> mujoco.MjData:
        data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, data)
        return data

    # --- kinematic state ------------------------------------------------------------------------------

    def set_state(self, data: mujoco.MjData, motions: dict[str, tuple[PlatformMotion, LegMotion]], sample: int) -> None:
        """qpos, qvel and qacc of every joint for one sample of `TwinInverseDynamics.platform_motion`.

        Rods take zero spin about their own axis (ω·u = 0): ω = u × u̇ and α = u × ü, which satisfies the loop
        constraints at velocity and acceleration level; the spin angle is free and does not change dynamics."""
        for robot_index, side in enumerate(self.twin.sides):
            platform, legs = motions[side]
            yaw = self._base_yaws[robot_index]
            base = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
            placement = self.twin.placement(side)
            rotation = platform.rotations[sample]
            qpos, dof = self.platform_qpos[robot_index], self.platform_dof[robot_index]
            data.qpos[qpos : qpos + 3] = np.asarray(placement.base_origin_m) + base @ platform.positions_m[sample]
            mujoco.mju_mat2Quat(data.qpos[qpos + 3 : qpos + 7], (base @ rotation).ravel())
            data.qvel[dof : dof + 3] = base @ platform.velocities_m_s[sample]
            data.qvel[dof + 3 : dof + 6] = rotation.T @ platform.angular_velocities_rad_s[sample]
            data.qacc[dof : dof + 3] = base @ platform.accelerations_m_s2[sample]
            data.qacc[dof + 3 : dof + 6] = rotation.T @ platform.angular_accelerations_rad_s2[sample]
            robot = self.twin.robot_for(side)
            for leg in range(6):
                axis = 6 * robot_index + leg
                data.qpos[self.slider_qpos[axis]] = legs.slider_positions_m[sample, leg]
                data.qvel[self.slider_dof[axis]] = legs.slider_velocities_m_s[sample, leg]
                data.qacc[self.slider_dof[axis]] = legs.slider_accelerations_m_s2[sample, leg]
                anchor = np.array([legs.slider_positions_m[sample, leg], robot.rail_y_m[leg], robot.rail_z_m])
                rod = legs.joint_positions_m[sample, leg] - anchor
                rod_rate = legs.joint_velocities_m_s[sample, leg] - [legs.slider_velocities_m_s[sample, leg], 0, 0]
                rod_acc = legs.joint_accelerations_m_s2[sample, leg] - [
                    legs.slider_accelerations_m_s2[sample, leg],
                    0,
                    0,
                ]
                length = robot.rod_length_m
                unit = rod / length
                neutral = self._neutral_rods[robot_index][leg] / length
                rod_rotation = _shortest_rotation(neutral, unit)
                mujoco.mju_mat2Quat(data.qpos[self.rod_qpos[axis] : self.rod_qpos[axis] + 4], rod_rotation.ravel())
                dof = self.rod_dof[axis]
                data.qvel[dof : dof + 3] = rod_rotation.T @ np.cross(unit, rod_rate / length)
                data.qacc[dof : dof + 3] = rod_rotation.T @ np.cross(unit, rod_acc / length)

    def inverse_slider_forces(self, twin_dynamics: TwinInverseDynamics, trajectory: StanceTrajectory) -> InverseResult:
        """MuJoCo's slider forces (N, 12) along a stance trajectory (see the module docstring)."""
        model = self.model
        data = mujoco.MjData(model)
        motions = twin_dynamics.platform_motion(trajectory.poses, trajectory.velocities, trajectory.accelerations)
        count = trajectory.poses.shape[0]
        forces = np.empty((count, 12))
        worst = 0.0
        saved_flags = model.opt.disableflags
        jac_a, jac_b = np.zeros((3, model.nv)), np.zeros((3, model.nv))
        system = np.zeros((model.nv, 12 + 3 * len(self.loop_sites)))
        system[self.slider_dof, np.arange(12)] = 1.0
        try:
            for sample in range(count):
                self.set_state(data, motions, sample)
                model.opt.disableflags = saved_flags | mujoco.mjtDisableBit.mjDSBL_CONSTRAINT
                mujoco.mj_inverse(model, data)
                generalized = data.qfrc_inverse.copy()
                for index, (site_a, site_b) in enumerate(self.loop_sites):
                    mujoco.mj_jacSite(model, data, jac_a, None, site_a)
                    mujoco.mj_jacSite(model, data, jac_b, None, site_b)
                    system[:, 12 + 3 * index : 15 + 3 * index] = (jac_a - jac_b).T
                solution, *_ = np.linalg.lstsq(system, generalized, rcond=None)
                residual = np.abs(system @ solution - generalized).max() / max(np.abs(generalized).max(), 1e-9)
                worst = max(worst, float(residual))
                forces[sample] = solution[:12]
        finally:
            model.opt.disableflags = saved_flags
        return InverseResult(forces, worst)

    # --- sensors ------------------------------------------------------------------------------------------

    def plate_readings(self, data: mujoco.MjData, force_z_out: np.ndarray, cop_out: np.ndarray) -> None:
        """Vertical load (N) on each foot plate and its centre of pressure (x, y, plate frame, m).

        MuJoCo reports the force and torque between the platform and the plate's subtree at the plate surface
        point, in the plate frame; a load pressing down reads +F_z. COP from that surface wrench:
        x = −M_y / F_z, y = M_x / F_z."""
        for foot in range(2):
            force = data.sensordata[self._plate_force_adr[foot] : self._plate_force_adr[foot] + 3]
            torque = data.sensordata[self._plate_torque_adr[foot] : self._plate_torque_adr[foot] + 3]
            load_z = force[2]
            force_z_out[foot] = load_z
            if load_z > 1e-6:
                cop_out[foot, 0] = -torque[1] / load_z
                cop_out[foot, 1] = torque[0] / load_z
            else:  # an unloaded plate has no centre of pressure
                cop_out[foot] = np.nan

    def harness_load_n(self, data: mujoco.MjData) -> float:
        if not self.has_harness:
            return 0.0
        stretch = data.sensordata[self._harness_adr] - self.options.harness.rest_length_m
        return self.options.harness.stiffness_n_m * stretch if stretch > 0.0 else 0.0


def _shortest_rotation(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Rotation matrix of the shortest arc taking unit `start` onto unit `end` (Rodrigues)."""
    axis = np.cross(start, end)
    cosine = float(start @ end)
    skew = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + skew + skew @ skew / (1.0 + cosine)
