"""The twin stepped in MuJoCo at the control rate with emulated drives and, optionally, a simulated patient.

Without a patient the payload is the rigid half-body per foot of `core.dynamics`; the plate sensors and the
harness tendon measure it. With a patient (`core.patient.SimulatedPatient`), each control period the patient
model is driven by the support motion (acceleration, roll/pitch and angular velocity of the platforms) and
its foot loads act on the foot plates: the load at the centre of pressure, along the plate's normal.

The mass the plates carry along is MuJoCo's: a point-mass body at each plate's origin (under the ankle) holds
that foot's share of the patient's mass, set every period from the patient's foot loads, so the support's
acceleration enters its inertia implicitly. Applying the carrying force m·a from the finite-differenced
acceleration of the last period instead closes a one-step loop with gain m / (the plate's own mass): it
diverged with a 120 kg patient. The explicit wrench takes back what MuJoCo already applies to those bodies
(their weight and the heave the patient model saw), so the plates feel the patient's loads once.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import mujoco
import numba
import numpy as np

from core.patient import PatientParameters, SimulatedPatient
from core.physics import GRAVITY_M_S2
from core.robot import TwinRobot
from server.hal.sim.drives import ServoDrives, ServoParameters
from server.hal.sim.mjcf import SimModelOptions
from server.hal.sim.model import TwinSimModel


@dataclass(frozen=True)
class SimulatorOptions:
    control_period_s: float = 0.001
    physics_substeps: int = 1
    model: SimModelOptions = field(default_factory=SimModelOptions)
    servo: ServoParameters = field(default_factory=ServoParameters)
    patient: PatientParameters | None = None
    patient_seed: int = 0


class TwinSimulator:
    """One MuJoCo data instance, the drives, and (optionally) the patient; `advance()` is one control period."""

    def __init__(self, twin: TwinRobot, options: SimulatorOptions | None = None) -> None:
        options = options or SimulatorOptions()
        if options.physics_substeps < 1:
            raise ValueError(f"physics_substeps = {options.physics_substeps}: must be >= 1")
        physics_dt = options.control_period_s / options.physics_substeps
        model_options = replace(options.model, timestep_s=physics_dt)
        if options.patient is not None:  # the patient's loads replace the rigid payload and its rope
            model_options = replace(model_options, payload=None, patient_mass_kg=options.patient.body_mass_kg)
        self.options = options
        self.twin = twin
        self.sim_model = TwinSimModel(twin, model_options)
        self.model = self.sim_model.model
        self.data = mujoco.MjData(self.model)
        self.drives = ServoDrives(options.servo)
        self.patient = (
            SimulatedPatient(options.patient, options.control_period_s, options.patient_seed)
            if options.patient is not None
            else None
        )
        self._actuator_bias = self.model.actuator_biasprm[:, :3]  # views into the model, written each step
        self._actuator_range = self.model.actuator_forcerange
        self._plate_bodies = np.array([self.model.body(f"{s}_foot_plate").id for s in twin.sides])
        self._plate_wrenches = np.zeros((2, 6))
        self._load_bodies = (
            np.array([self.model.body(f"{s}_patient_load").id for s in twin.sides])
            if self.patient is not None
            else None
        )
        self._load_masses = np.zeros(2)
        self._positions = np.zeros(12)
        self._velocities = np.zeros(12)
        self._previous_support_velocity = np.zeros(3)
        self._support_acceleration = np.zeros(3)
        self._support_tilt = np.zeros(2)
        self._support_omega = np.zeros(3)
        self.harness_load_n = 0.0
        self.plate_force_z_n = np.zeros(2)
        self.plate_cop_m = np.zeros((2, 2))
        self.reset()

    def reset(self) -> None:
        mujoco.mj_resetData(self.model, self.data)
        mujoco.mj_forward(self.model, self.data)
        self._read_axes()
        self.drives.brake_position_m[:] = self._positions
        self._previous_support_velocity[:] = 0.0
        if self.patient is not None:
            self.patient.reset()

    @property
    def time_s(self) -> float:
        return float(self.data.time)

    @property
    def positions_m(self) -> np.ndarray:
        return self._positions

    @property
    def velocities_m_s(self) -> np.ndarray:
        return self._velocities

    def advance(self) -> None:
        """One control period: patient loads, then the drives and MuJoCo at the physics rate."""
        if self.patient is not None:
            self._apply_patient_loads()
        dt = self.model.opt.timestep
        drives = self.drives
        for _ in range(self.options.physics_substeps):
            drives.update(self._positions, self._velocities, dt)
            np.copyto(self.data.ctrl, drives.ctrl)
            np.copyto(self._actuator_bias, drives.bias)
            np.copyto(self._actuator_range[:, 1], drives.force_range_n)
            np.negative(drives.force_range_n, out=self._actuator_range[:, 0])
            mujoco.mj_step(self.model, self.data)
            self._read_axes()
        np.copyto(drives.forces_n, self.data.actuator_force)  # what the actuators applied, limits included
        self._read_sensors()

    def _read_axes(self) -> None:
        self._positions[:] = self.data.qpos[self.sim_model.slider_qpos]
        self._velocities[:] = self.data.qvel[self.sim_model.slider_dof]

    def _read_sensors(self) -> None:
        if self.patient is None:  # mj_step evaluated the sensors at the start of the last physics step
            self.sim_model.plate_readings(self.data, self.plate_force_z_n, self.plate_cop_m)
            self.harness_load_n = self.sim_model.harness_load_n(self.data)

    def _apply_patient_loads(self) -> None:
        assert self.patient is not None
        data, dof = self.data, self.sim_model.platform_dof
        platform = self.sim_model.platform_body[0]
        _support_motion(
            data.qvel[dof[0] : dof[0] + 6],
            data.qvel[dof[1] : dof[1] + 6],
            data.xmat[platform],
            self.options.control_period_s,
            self._previous_support_velocity,
            self._support_acceleration,
            self._support_tilt,
            self._support_omega,
        )
        sample = self.patient.step(self._support_acceleration, self._support_tilt, self._support_omega)
        _foot_wrenches(
            data.xpos[self._plate_bodies],
            data.xmat[self._plate_bodies],
            data.xipos[self._plate_bodies],
            sample.plate_force_z_n,
            sample.plate_cop_m,
            self.patient.params.body_mass_kg,
            self._support_acceleration,
            self._load_masses,
            self._plate_wrenches,
        )
        self.model.body_mass[self._load_bodies] = self._load_masses
        data.xfrc_applied[self._plate_bodies] = self._plate_wrenches
        self.plate_force_z_n[:] = sample.plate_force_z_n
        self.plate_cop_m[:] = sample.plate_cop_m
        self.harness_load_n = sample.harness_load_n


@numba.njit(cache=True)
def _support_motion(
    right_velocity: np.ndarray,
    left_velocity: np.ndarray,
    rotation: np.ndarray,
    period_s: float,
    previous_velocity: np.ndarray,
    acceleration_out: np.ndarray,
    tilt_out: np.ndarray,
    omega_out: np.ndarray,
) -> None:
    """Support acceleration (finite difference of the platforms' mean velocity), roll/pitch (R = Rx·Ry·Rz,
    `rotation` flat row-major) and angular velocity in the world frame (free-joint ω is body-local)."""
    for i in range(3):
        velocity = 0.5 * (right_velocity[i] + left_velocity[i])
        acceleration_out[i] = (velocity - previous_velocity[i]) / period_s
        previous_velocity[i] = velocity
        omega_out[i] = (
            rotation[3 * i] * right_velocity[3]
            + rotation[3 * i + 1] * right_velocity[4]
            + rotation[3 * i + 2] * right_velocity[5]
        )
    tilt_out[0] = np.arctan2(-rotation[5], rotation[8])
    tilt_out[1] = np.arcsin(min(max(rotation[2], -1.0), 1.0))


@numba.njit(cache=True)
def _foot_wrenches(
    plate_positions: np.ndarray,
    plate_rotations: np.ndarray,
    plate_coms: np.ndarray,
    force_z: np.ndarray,
    cop: np.ndarray,
    body_mass_kg: float,
    support_acceleration: np.ndarray,
    load_masses_out: np.ndarray,
    wrenches_out: np.ndarray,
) -> None:
    """Each foot's share of the patient's mass (for the plate's load body) and the world wrench (force, torque
    about the plate body's COM) of that foot on its plate: the load at the centre of pressure along the
    plate's normal, less what MuJoCo applies to the load body itself, its weight and the heave inertia
    m·a_z (a_z the support acceleration the patient model was given), at the plate's origin."""
    total = force_z[0] + force_z[1]
    for foot in range(2):
        rotation = plate_rotations[foot]
        share = body_mass_kg * force_z[foot] / total if total > 0.0 else 0.0
        load_masses_out[foot] = share
        force = np.empty(3)
        for i in range(3):
            force[i] = -force_z[foot] * rotation[3 * i + 2]
        point = np.empty(3)
        for i in range(3):
            point[i] = plate_positions[foot, i] + rotation[3 * i] * cop[foot, 0] + rotation[3 * i + 1] * cop[foot, 1]
        lever = point - plate_coms[foot]
        torque = np.cross(lever, force)
        lift = share * (GRAVITY_M_S2 + support_acceleration[2])  # upward, at the load body (plate origin)
        origin_lever = plate_positions[foot] - plate_coms[foot]
        wrenches_out[foot, 0:2] = force[0:2]
        wrenches_out[foot, 2] = force[2] + lift
        wrenches_out[foot, 3] = torque[0] + origin_lever[1] * lift
        wrenches_out[foot, 4] = torque[1] - origin_lever[0] * lift
        wrenches_out[foot, 5] = torque[2]
