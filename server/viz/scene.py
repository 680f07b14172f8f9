"""The twin robot's 3D scene in viser: built once from the `TwinRobot` geometry, then moved by poses only.

Both 6-SSP robots (paper §2.2, REFERENCE.md §1): rails along each base's X axis, a slider per leg at
`(s_i, rail_y_i, rail_z)` in its base frame, a constant-length rod from slider to platform joint
`W_i = p + R·B_i` (Formula (10)), the platform and its foot plate, and a simple standing patient carried
by the stance frame (`core.kinematics.twin_platform_poses`). Every node is added in `TwinScene.__init__`;
`show()` only assigns `.position`/`.wxyz` inside `server.atomic()`, as the viser examples do.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from core.kinematics import rotation_matrices, stance_origin_world, twin_platform_poses
from core.robot import TwinRobot

SLIDER_SIZE_M = (0.14, 0.10, 0.06)
ROD_RADIUS_M = 0.014
RAIL_RADIUS_M = 0.02
PLATFORM_THICKNESS_M = 0.04
FOOT_PLATE_SIZE_M = (0.30, 0.14, 0.02)
FIGURE_HEIGHT_M = 1.70  # a generic adult until the page names the patient's height (never who it is)
FIGURE_HEIGHT_RANGE_M = (0.5, 2.5)  # the patient record's own range (server.patients.schemas.HeightM)
# Where the patient faces and which foot is which (stance frame: x forward, y to the patient's left).
DIRECTION_LABELS = {"front": ("FRONT: the patient faces this way", (1.05, 0.0, 0.05)),
                    "left": ("LEFT foot side", (0.0, 0.75, 0.05)),
                    "right": ("RIGHT foot side", (0.0, -0.75, 0.05))}  # fmt: skip

COLOURS = {
    "rail": (70, 70, 80),
    "slider": (240, 190, 20),
    "rod": (150, 160, 175),
    "platform": (60, 110, 180),
    "foot_right": (230, 120, 30),
    "foot_left": (20, 160, 150),
    "patient": (200, 200, 210),
    "floor": (235, 235, 235),
}


@dataclass(frozen=True)
class TwinPose:
    """Where every moving part is, in the world frame: what one frame of the view shows."""

    platform_positions_m: np.ndarray  # (2, 3) right, left
    platform_rotations: np.ndarray  # (2, 3, 3)
    slider_joints_m: np.ndarray  # (12, 3): right sliders 1-6 then left 1-6 (HAL axis order)
    platform_joints_m: np.ndarray  # (12, 3)
    stance_position_m: np.ndarray  # (3,)
    stance_rotation: np.ndarray  # (3, 3)


def _yaw_matrix(yaw_rad: float) -> np.ndarray:
    c, s = np.cos(yaw_rad), np.sin(yaw_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def wxyz_from_matrices(rotations: np.ndarray) -> np.ndarray:
    """Unit quaternions (..., 4) as viser wants them, (w, x, y, z), of rotation matrices (..., 3, 3)."""
    m = np.asarray(rotations, dtype=float)
    return Rotation.from_matrix(m.reshape(-1, 3, 3)).as_quat(scalar_first=True).reshape(*m.shape[:-2], 4)


def wxyz_z_to(directions: np.ndarray) -> np.ndarray:
    """Quaternions (N, 4) turning +Z onto each direction (N, 3): how a cylinder (axis Z) lies along a rod."""
    d = directions / np.linalg.norm(directions, axis=-1, keepdims=True)
    # q ∝ (1 + z·d, z × d); opposite to Z there is no unique axis, so turn about X.
    q = np.stack([1.0 + d[:, 2], -d[:, 1], d[:, 0], np.zeros(len(d))], axis=-1)
    flipped = q[:, 0] < 1e-9
    q[flipped] = (0.0, 1.0, 0.0, 0.0)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


class TwinGeometry:
    """World-frame placement of both robots: turns a stance pose and 12 slider positions into a `TwinPose`."""

    def __init__(self, twin: TwinRobot) -> None:
        self.twin = twin
        self.base_origins_m = np.array([twin.placement(side).base_origin_m for side in twin.sides])
        self.base_yaws = np.array([_yaw_matrix(twin.placement(side).base_yaw_rad) for side in twin.sides])
        self.robots = [twin.robot_for(side) for side in twin.sides]
        self.platform_joints_local_m = np.array([robot.platform_joints_m for robot in self.robots])  # (2, 6, 3)
        self.rail_y_m = np.array([robot.rail_y_m for robot in self.robots])  # (2, 6)
        self.rail_z_m = np.array([robot.rail_z_m for robot in self.robots])  # (2,)
        self.stance_origin_m = stance_origin_world(twin)
        self.neutral_sliders_m = self._neutral_sliders()

    def _neutral_sliders(self) -> np.ndarray:
        from core.kinematics import twin_inverse_kinematics

        solutions = twin_inverse_kinematics(self.twin, np.zeros((1, 6)))
        return np.concatenate([solutions[side].slider_positions_m[0] for side in self.twin.sides])

    def to_world(self, side_index: int, points_base: np.ndarray) -> np.ndarray:
        return self.base_origins_m[side_index] + points_base @ self.base_yaws[side_index].T

    def pose(self, stance_pose: np.ndarray, slider_positions_m: np.ndarray) -> TwinPose:
        """Stance pose (6,) (m, rad; relative to neutral) and slider positions (12,) along the rails, m."""
        stance_pose = np.asarray(stance_pose, dtype=float).reshape(6)
        sliders = np.asarray(slider_positions_m, dtype=float).reshape(2, 6)
        platforms = twin_platform_poses(self.twin, stance_pose[None, :])
        positions, rotations, slider_joints, platform_joints = [], [], [], []
        for index, side in enumerate(self.twin.sides):
            position_base, rotation_base = platforms[side][0][0], platforms[side][1][0]
            position = self.to_world(index, position_base)
            rotation = self.base_yaws[index] @ rotation_base
            rails = np.stack([sliders[index], self.rail_y_m[index], np.full(6, self.rail_z_m[index])], axis=-1)
            positions.append(position)
            rotations.append(rotation)
            slider_joints.append(self.to_world(index, rails))
            platform_joints.append(position + self.platform_joints_local_m[index] @ rotation.T)
        return TwinPose(
            platform_positions_m=np.array(positions),
            platform_rotations=np.array(rotations),
            slider_joints_m=np.concatenate(slider_joints),
            platform_joints_m=np.concatenate(platform_joints),
            stance_position_m=self.stance_origin_m + stance_pose[:3],
            stance_rotation=rotation_matrices(stance_pose[None, 3:])[0],
        )


class TwinScene:
    """The viser scene of the twin robot. Nodes are created here, once; `show` only moves them."""

    def __init__(self, server: Any, twin: TwinRobot, *, root: str = "/twin") -> None:
        self.server = server
        self.geometry = TwinGeometry(twin)
        self.rod_length_m = twin.robot.rod_length_m
        self.frames_shown = 0
        scene = server.scene
        scene.add_grid(f"{root}/floor", width=5.0, height=5.0, cell_size=0.25, plane="xy", position=(0.0, 0.0, -0.001))
        self._add_rails(scene, root)
        self.sliders = [
            scene.add_box(f"{root}/slider_{i}", color=COLOURS["slider"], dimensions=SLIDER_SIZE_M) for i in range(12)
        ]
        self.rods = [
            scene.add_cylinder(
                f"{root}/rod_{i}",
                radius=ROD_RADIUS_M,
                height=self.rod_length_m,
                color=COLOURS["rod"],
                radial_segments=12,
            )
            for i in range(12)
        ]
        self.platforms = [self._add_platform(scene, root, index, side) for index, side in enumerate(twin.sides)]
        self.labels = {
            name: scene.add_label(f"{root}/labels/{name}", text, position=position, font_screen_scale=1.2)
            for name, (text, position) in DIRECTION_LABELS.items()
        }
        self.root = root
        self.figure_height_m = FIGURE_HEIGHT_M
        self.figure_parts: list[Any] = []
        self.patient = self._add_patient(scene, root)
        self.show(np.zeros(6), self.geometry.neutral_sliders_m)

    def set_figure_height(self, height_m: float) -> bool:
        """Rebuilds the figure at this standing height (m); False if it already has it. The figure's
        proportions are a generic adult's: only the height follows the patient."""
        low, high = FIGURE_HEIGHT_RANGE_M
        if not low <= height_m <= high:
            raise ValueError(f"height_m = {height_m!r}: must be in [{low:g}, {high:g}] m")
        if abs(height_m - self.figure_height_m) < 1e-4:
            return False
        with self.server.atomic():
            for part in self.figure_parts:
                part.remove()
            self.figure_height_m = float(height_m)
            self.figure_parts = self._add_figure(self.server.scene, self.root)
        return True

    def _add_rails(self, scene: Any, root: str) -> None:
        """Static: one rail per distinct rail line of each robot, spanning both halves' strokes."""
        for index, robot in enumerate(self.geometry.robots):
            x_min, x_max = float(np.min(robot.stroke_min_m)), float(np.max(robot.stroke_max_m))
            for rail_y in sorted(set(robot.rail_y_m.tolist())):
                ends = self.geometry.to_world(
                    index, np.array([[x_min, rail_y, robot.rail_z_m], [x_max, rail_y, robot.rail_z_m]])
                )
                scene.add_cylinder(
                    f"{root}/{self.geometry.twin.sides[index]}/rail_{rail_y:+.3f}",
                    radius=RAIL_RADIUS_M,
                    height=float(np.linalg.norm(ends[1] - ends[0])),
                    color=COLOURS["rail"],
                    position=tuple(ends.mean(axis=0)),
                    wxyz=tuple(wxyz_z_to((ends[1] - ends[0])[None, :])[0]),
                )

    def _add_platform(self, scene: Any, root: str, index: int, side: str) -> Any:
        """A frame carrying the hexagonal plate (through the six joints B_i) and the foot plate."""
        frame = scene.add_frame(f"{root}/{side}/platform", show_axes=False)
        joints = self.geometry.platform_joints_local_m[index]
        order = np.argsort(np.arctan2(joints[:, 1], joints[:, 0]))
        ring = joints[order]
        bottom = ring - np.array([0.0, 0.0, PLATFORM_THICKNESS_M])
        vertices = np.concatenate([ring, bottom, [[0.0, 0.0, 0.0], [0.0, 0.0, -PLATFORM_THICKNESS_M]]])
        faces = []
        for k in range(6):
            n = (k + 1) % 6
            faces += [[12, k, n], [13, 6 + n, 6 + k], [k, 6 + k, 6 + n], [k, 6 + n, n]]
        scene.add_mesh_simple(
            f"{root}/{side}/platform/plate",
            vertices=vertices.astype(np.float32),
            faces=np.array(faces, dtype=np.uint32),
            color=COLOURS["platform"],
            side="double",
        )
        offset = np.asarray(self.geometry.twin.placement(side).foot_plate_offset_m, dtype=float)
        scene.add_box(
            f"{root}/{side}/platform/foot_plate",
            color=COLOURS[f"foot_{side}"],
            dimensions=FOOT_PLATE_SIZE_M,
            position=tuple(offset + np.array([0.0, 0.0, FOOT_PLATE_SIZE_M[2] / 2])),
        )
        return frame

    def _add_patient(self, scene: Any, root: str) -> Any:
        """A plain standing figure on the two foot plates, carried by the stance frame."""
        frame = scene.add_frame(f"{root}/patient", show_axes=False)
        self.figure_parts = self._add_figure(scene, root)
        return frame

    def _add_figure(self, scene: Any, root: str) -> list[Any]:
        feet_y = [
            float(
                (
                    self.geometry.to_world(i, np.asarray(self.geometry.robots[i].neutral_pose[:3]))
                    + self.geometry.base_yaws[i] @ np.asarray(self.geometry.twin.placement(side).foot_plate_offset_m)
                    - self.geometry.stance_origin_m
                )[1]
            )
            for i, side in enumerate(self.geometry.twin.sides)
        ]
        h = self.figure_height_m
        scale = h / FIGURE_HEIGHT_M
        base = FOOT_PLATE_SIZE_M[2]
        hip_z, shoulder_z = base + 0.53 * h, base + 0.82 * h
        hip_half_width = 0.09 * scale
        colour = COLOURS["patient"]
        parts = []
        for index, foot_y in enumerate(feet_y):
            bottom = np.array([0.0, foot_y, base])
            top = np.array([0.0, np.sign(foot_y) * hip_half_width, hip_z])
            parts.append(self._add_limb(scene, f"{root}/patient/leg_{index}", bottom, top, 0.06 * scale, colour))
            arm_top = np.array([0.0, np.sign(foot_y) * 0.2 * scale, shoulder_z])
            arm_bottom = np.array([0.02, np.sign(foot_y) * 0.24 * scale, shoulder_z - 0.33 * h])
            parts.append(
                self._add_limb(scene, f"{root}/patient/arm_{index}", arm_bottom, arm_top, 0.04 * scale, colour)
            )
        torso = (np.array([0.0, 0.0, hip_z]), np.array([0.0, 0.0, shoulder_z]))
        parts.append(self._add_limb(scene, f"{root}/patient/torso", *torso, 0.15 * scale, colour))
        head_radius = 0.11 * scale
        parts.append(scene.add_icosphere(f"{root}/patient/head", radius=head_radius, color=colour,
                                         position=(0.0, 0.0, shoulder_z + 0.14 * scale)))  # fmt: skip
        return parts

    @staticmethod
    def _add_limb(scene: Any, name: str, start: np.ndarray, end: np.ndarray, radius: float, colour: tuple) -> Any:
        return scene.add_cylinder(
            name,
            radius=radius,
            height=float(np.linalg.norm(end - start)),
            color=colour,
            position=tuple((start + end) / 2),
            wxyz=tuple(wxyz_z_to((end - start)[None, :])[0]),
        )

    def show(self, stance_pose: np.ndarray, slider_positions_m: np.ndarray) -> TwinPose:
        """Move every part to this stance pose (6,) and these slider positions (12,) in one atomic update."""
        pose = self.geometry.pose(stance_pose, slider_positions_m)
        platform_wxyz = wxyz_from_matrices(pose.platform_rotations)
        rods = pose.platform_joints_m - pose.slider_joints_m
        rod_wxyz = wxyz_z_to(rods)
        # The rod keeps its length: it starts at the slider and points at the platform joint.
        rod_centres = pose.slider_joints_m + rods / np.linalg.norm(rods, axis=-1, keepdims=True) * (
            self.rod_length_m / 2
        )
        with self.server.atomic():
            for i in range(12):
                self.sliders[i].position = pose.slider_joints_m[i]
                self.rods[i].position = rod_centres[i]
                self.rods[i].wxyz = rod_wxyz[i]
            for i, frame in enumerate(self.platforms):
                frame.position = pose.platform_positions_m[i]
                frame.wxyz = platform_wxyz[i]
            self.patient.position = pose.stance_position_m
            self.patient.wxyz = wxyz_from_matrices(pose.stance_rotation)
        self.frames_shown += 1
        return pose
