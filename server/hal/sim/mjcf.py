"""The twin robot as MJCF, generated from `TwinRobot` (never a hand-written file).

Each robot: six sliders on slide joints (force actuators along their rails, with an affine bias), six rods
hanging from the sliders on ball joints, and a free platform; each rod's far end is tied to its platform
joint by a `connect` equality constraint, which closes the six loops. On each platform sits a foot plate
with a 6-axis force/torque sensor and, optionally, half of a rigid patient (`core.dynamics.PayloadModel`,
the split `TwinInverseDynamics` uses). A harness rope (a spatial tendon, slack below its rest length) runs
from a fixed anchor above the stance origin to the patient's chest. Contacts are disabled: nothing touches.

Coordinates: slider joint positions are the slider x along the rail in the base frame (the joint `ref` is
the neutral slider position), so MuJoCo's slider qpos equals the kinematics' slider position.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from xml.sax.saxutils import quoteattr

import numpy as np

from core.dynamics import PayloadModel, payload_body
from core.kinematics import inverse_kinematics, rotation_matrices, stance_origin_world, yaw_matrix
from core.physics import GRAVITY_M_S2
from core.robot import SSPRobot, TwinRobot

ROD_RADIUS_M = 0.02  # a 40 mm tube: only its spin inertia uses it, and spin never changes the dynamics


@dataclass(frozen=True)
class HarnessRope:
    """The harness rope: a tendon from an anchor above the stance origin to the patient's chest."""

    attachment_height_m: float = 1.26  # above the foot plates (0.72 of a 1.75 m body)
    anchor_above_attachment_m: float = 1.0
    slack_m: float = 0.05
    stiffness_n_m: float = 10_000.0
    damping_n_s_m: float = 300.0

    @property
    def rest_length_m(self) -> float:
        return self.anchor_above_attachment_m + self.slack_m


@dataclass(frozen=True)
class SimModelOptions:
    timestep_s: float = 0.001
    payload: PayloadModel | None = field(default_factory=lambda: PayloadModel.from_body(75.0, 1.75))
    include_rods: bool = True
    harness: HarnessRope = field(default_factory=HarnessRope)
    # Closed-loop constraints: as stiff as the time step allows (solref time constant 2·dt, critically
    # damped) with impedance 0.9999, so that the loops yield by 0.01 % of the unconstrained acceleration.
    constraint_solimp: tuple[float, float, float] = (0.9999, 0.9999, 0.001)
    integrator: str = "implicitfast"
    # Contacts between the rods and between the platforms (and their foot plates): an independent
    # cross-check of core.clearance. Off by default: the servo and dynamics cross-checks were calibrated
    # without, and a layout that can be built never touches (issue 13).
    contacts: bool = False
    # A simulated patient's mass (kg), carried by a point-mass body at each foot plate's origin (under the
    # ankle) so that MuJoCo solves the mass the plates carry along implicitly; the simulator sets each
    # foot's share every control period. 0: no such bodies.
    patient_mass_kg: float = 0.0


def _vector(values: np.ndarray) -> str:
    return " ".join(f"{float(v):.10g}" for v in np.ravel(values))


def _quaternion(rotation: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix (MuJoCo's order)."""
    import mujoco

    quaternion = np.empty(4)
    mujoco.mju_mat2Quat(quaternion, np.ascontiguousarray(rotation, dtype=float).ravel())
    return quaternion


def _quaternion_z_to(direction: np.ndarray) -> np.ndarray:
    """The shortest rotation taking +Z onto `direction` (unit)."""
    import mujoco

    quaternion = np.empty(4)
    mujoco.mju_quatZ2Vec(quaternion, np.ascontiguousarray(direction, dtype=float))
    return quaternion


def neutral_rod_vectors(robot: SSPRobot) -> tuple[np.ndarray, np.ndarray]:
    """Neutral slider positions (6,) and rod vectors slider joint → platform joint (6, 3), base frame."""
    neutral = np.asarray(robot.neutral_pose, dtype=float)
    sliders = inverse_kinematics(robot, neutral).slider_positions_m[0]
    joints = neutral[:3] + robot.platform_joints_m @ rotation_matrices(neutral[None, 3:])[0].T
    anchors = np.stack([sliders, robot.rail_y_m, np.full(6, robot.rail_z_m)], axis=1)
    return sliders, joints - anchors


def _inertial(mass: float, com: np.ndarray, inertia: np.ndarray) -> str:
    full = (inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2])
    return f'<inertial pos="{_vector(com)}" mass="{mass:.10g}" fullinertia="{_vector(np.array(full))}"/>'


def _robot_xml(twin: TwinRobot, side: str, options: SimModelOptions, lines: list[str], equalities: list[str]) -> None:
    placement, robot = twin.placement(side), twin.robot_for(side)
    base_rotation = yaw_matrix(placement.base_yaw_rad)
    base_origin = np.asarray(placement.base_origin_m, dtype=float)
    base_quat = _quaternion(base_rotation)
    neutral_sliders, rods = neutral_rod_vectors(robot)
    mass = robot.mass
    rod_mass = mass.rod_mass_kg if options.include_rods else 0.0
    length = robot.rod_length_m
    # Rods and platforms collide with each other; every other geom keeps contype = conaffinity = 0.
    contact = ' contype="1" conaffinity="1"' if options.contacts else ""
    for index in range(6):
        name = f"{side}_slider{index + 1}"
        position = base_origin + base_rotation @ np.array(
            [neutral_sliders[index], robot.rail_y_m[index], robot.rail_z_m]
        )
        low, high = robot.stroke_min_m[index], robot.stroke_max_m[index]
        rod = rods[index]
        lines += [
            f'<body name="{name}" pos="{_vector(position)}" quat="{_vector(base_quat)}">',
            f'  <joint name="{name}" type="slide" axis="1 0 0" ref="{neutral_sliders[index]:.10g}" '
            f'range="{low:.10g} {high:.10g}"/>',
            f'  <inertial pos="0 0 0" mass="{mass.slider_mass_kg:.10g}" diaginertia="0.05 0.05 0.05"/>',
            '  <geom type="box" size="0.06 0.04 0.03" rgba="0.3 0.3 0.35 1"/>',
            f'  <body name="{side}_rod{index + 1}">',
            f'    <joint name="{side}_rod{index + 1}" type="ball"/>',
        ]
        if rod_mass > 0.0:
            transverse = rod_mass * length**2 / 12.0  # uniform slender rod about its centre
            axial = 0.5 * rod_mass * ROD_RADIUS_M**2
            lines.append(
                f'    <inertial pos="{_vector(rod / 2)}" quat="{_vector(_quaternion_z_to(rod / length))}" '
                f'mass="{rod_mass:.10g}" diaginertia="{transverse:.10g} {transverse:.10g} {axial:.10g}"/>'
            )
        else:  # a moving body needs some mass; a gram at the slider joint does not change the forces
            lines.append('    <inertial pos="0 0 0" mass="0.001" diaginertia="1e-6 1e-6 1e-6"/>')
        lines += [
            f'    <geom name="{side}_rod{index + 1}" type="capsule" fromto="0 0 0 {_vector(rod)}" '
            f'size="{ROD_RADIUS_M}" rgba="0.7 0.7 0.75 1"{contact}/>',
            f'    <site name="{side}_rod{index + 1}_end" pos="{_vector(rod)}"/>',
            "  </body>",
            "</body>",
        ]
        equalities.append(
            f'<connect name="{side}_loop{index + 1}" site1="{side}_rod{index + 1}_end" '
            f'site2="{side}_platform_joint{index + 1}"/>'
        )

    neutral = np.asarray(robot.neutral_pose, dtype=float)
    neutral_world = base_rotation @ rotation_matrices(neutral[None, 3:])[0]
    platform_position = base_origin + base_rotation @ neutral[:3]
    lines += [
        f'<body name="{side}_platform" pos="{_vector(platform_position)}" '
        f'quat="{_vector(_quaternion(neutral_world))}">',
        f'  <freejoint name="{side}_platform"/>',
        _inertial(mass.platform_mass_kg, np.asarray(mass.platform_com_m), np.diag(mass.platform_inertia_kg_m2)),
        f'  <geom name="{side}_platform" type="cylinder" size="{robot.platform_radius_m:.4f} 0.02" pos="0 0 -0.02" '
        f'rgba="0.2 0.45 0.7 1"{contact}/>',
    ]
    for index, joint in enumerate(robot.platform_joints_m, start=1):
        lines.append(f'  <site name="{side}_platform_joint{index}" pos="{_vector(joint)}"/>')
    plate = np.asarray(placement.foot_plate_offset_m, dtype=float)
    lines += [
        f'  <body name="{side}_foot_plate" pos="{_vector(plate)}">',
        f'    <geom name="{side}_foot_plate" type="box" size="0.15 0.08 0.005" pos="0 0 0.005" '
        f'rgba="0.8 0.6 0.3 1"{contact}/>',
        f'    <site name="{side}_plate" pos="0 0 0"/>',
    ]
    if options.payload is not None and options.payload.mass_kg > 0.0:
        share = payload_body(options.payload.scaled(0.5), np.zeros(3), neutral_world.T)
        lines += [
            f'    <body name="{side}_payload">',
            "      " + _inertial(share.mass_kg, share.com_m, share.inertia_kg_m2),
            f'      <geom type="capsule" fromto="0 0 0.1 {_vector(share.com_m * [1, 1, 1.6])}" size="0.07" '
            'rgba="0.85 0.7 0.6 0.6"/>',
        ]
        if side == "right":
            # The chest harness point, above the stance origin (the rope loads the right robot only).
            attachment = neutral_world.T @ (stance_origin_world(twin) - platform_position) - plate
            attachment[2] += options.harness.attachment_height_m
            lines.append(f'      <site name="harness_attachment" pos="{_vector(attachment)}"/>')
        lines.append("    </body>")
    if options.patient_mass_kg > 0.0:
        lines += [
            f'    <body name="{side}_patient_load">',
            f'      <inertial pos="0 0 0" mass="{0.5 * options.patient_mass_kg:.10g}" diaginertia="1e-6 1e-6 1e-6"/>',
            "    </body>",
        ]
    lines += ["  </body>", "</body>"]


def twin_mjcf(twin: TwinRobot, options: SimModelOptions | None = None) -> str:
    """The MJCF document of the twin, neutral pose as the reference configuration (qpos0)."""
    options = options or SimModelOptions()
    lines: list[str] = []
    equalities: list[str] = []
    harness = options.harness
    has_payload = options.payload is not None and options.payload.mass_kg > 0.0
    anchor = stance_origin_world(twin) + np.array(
        [0.0, 0.0, harness.attachment_height_m + harness.anchor_above_attachment_m]
    )
    lines.append(f'<site name="harness_anchor" pos="{_vector(anchor)}"/>')
    for side in twin.sides:
        _robot_xml(twin, side, options, lines, equalities)
    timeref = 2.0 * options.timestep_s
    solimp = _vector(np.asarray(options.constraint_solimp))
    body = "\n    ".join(lines)
    equality = "\n    ".join(equalities)
    # A rod meets its own platform at its spherical joint: that pair shares a joint, it is no contact.
    excludes = "\n    ".join(
        f'<exclude body1="{side}_rod{i}" body2="{side}_platform"/>' for side in twin.sides for i in range(1, 7)
    )
    option_attributes = (
        f'timestep="{options.timestep_s:.10g}" gravity="0 0 {-GRAVITY_M_S2:.10g}" integrator="{options.integrator}"'
    )
    contact_flag = "" if options.contacts else '\n    <flag contact="disable"/>'
    contact_section = f"<contact>\n    {excludes}\n  </contact>" if options.contacts else ""
    # Actuator force = ctrl + b0 + b1·q + b2·q̇: the drives put their damping and the brake's spring in the
    # affine bias so that the implicit integrator treats them implicitly (stable at stiff gains).
    force_limit = twin.robot.limits.drive_force_max_n
    actuators = "\n    ".join(
        f'<general name="{side}_slider{i}" joint="{side}_slider{i}" gainprm="1" biastype="affine" '
        f'biasprm="0 0 0" forcelimited="true" forcerange="{-force_limit:.10g} {force_limit:.10g}"/>'
        for side in twin.sides
        for i in range(1, 7)
    )
    plate_sensors = "\n    ".join(
        f'<force name="{side}_plate_force" site="{side}_plate"/>\n    '
        f'<torque name="{side}_plate_torque" site="{side}_plate"/>'
        for side in twin.sides
    )
    tendon = ""
    if has_payload:
        tendon = (
            f'<tendon>\n    <spatial name="harness" springlength="0 {harness.rest_length_m:.10g}" '
            f'stiffness="{harness.stiffness_n_m:.10g}" damping="0">\n'
            '      <site site="harness_anchor"/>\n      <site site="harness_attachment"/>\n    </spatial>\n  </tendon>'
        )
        plate_sensors += '\n    <tendonpos name="harness_length" tendon="harness"/>'
    return f"""<mujoco model={quoteattr("ssp_rehab_twin")}>
  <compiler angle="radian" inertiafromgeom="false" autolimits="true"/>
  <option {option_attributes}>{contact_flag}
  </option>
  <default>
    <equality solref="{timeref:.10g} 1" solimp="{solimp}"/>
    <geom contype="0" conaffinity="0"/>
  </default>
  <worldbody>
    {body}
  </worldbody>
  <equality>
    {equality}
  </equality>
  {contact_section}
  {tendon}
  <actuator>
    {actuators}
  </actuator>
  <sensor>
    {plate_sensors}
  </sensor>
</mujoco>
"""
