"""Collision and clearance of the twin's physical parts (issue 13 §1): reachability includes them.

Every part is a capsule, a segment swept by a sphere (`core.robot.PartDimensions`): each rod (slider
joint to platform joint), each slider (along its rail), each rail (static), and each platform (the edges
of its joint hexagon, the arm from its centre to the foot plate, and the foot plate's two long edges).
The clearance of two capsules is the distance between their segments less both radii.

Pairs that share a joint are not checked: a rod with its slider, its own rail (its slider joint lies on
the rail axis in this model) and its own platform; a slider with its rail; the parts of one platform with
each other; the rails with each other (they never move). Platform against platform is checked once per
twin: both platforms move as one rigid body with the stance frame, so their clearance does not change
with the pose. Everything else, across both robots (rod–rod, rod–rail, rod–slider, rod–platform,
slider–slider, slider–platform, slider–rail), is checked per pose in one compiled kernel, which screens
each pair with its bounding boxes against the closest pair found so far and computes the exact distance
only where the boxes leave it open: the minimum is exact.
"""

from __future__ import annotations

import enum
import functools
import math
from dataclasses import dataclass, replace
from typing import NamedTuple

import numba
import numpy as np

from core.kinematics.ik import IKSolution, LegViolation, PoseCollisions, for_each_chunk
from core.kinematics.rotations import yaw_matrix
from core.kinematics.twin import twin_inverse_kinematics, twin_platform_poses
from core.robot import TwinRobot

NOTHING_CLOSER = "no pair closer than the reported bound"
# The twin IK needs the exact clearance only near the margins (the prescription check's stop margin is
# 20 mm more); farther than this it reports the bound, which lets the kernel skip most pairs.
IK_EXACT_BELOW_M = 0.10
# The extra clearance normal motion keeps so that a controlled stop can brake before parts meet (the plan's
# default `clearance_margin_m`, and the optimal planner's default).
STOP_CLEARANCE_MARGIN_M = 0.02
# Poses per block of the batch's broad phase: parts move little in this many control ticks, so the boxes they
# sweep stay tight, and most pairs are ruled out once per block instead of at every pose.
BROAD_PHASE_POSES = 64


class PartKind(enum.IntEnum):
    ROD = 0  # endpoints: the slider joint (slider x, rail y, rail z) and the platform joint p + R·B
    SLIDER = 1  # the slider joint ± half the slider length along the rail
    RAIL = 2  # static, base frame
    PLATFORM = 3  # fixed in the platform frame: world = o + Y·(p + R·local)


@dataclass(frozen=True)
class PartTable:
    """The twin's capsules, as arrays the kernels read."""

    names: tuple[str, ...]
    kind: np.ndarray  # (P,) PartKind
    robot: np.ndarray  # (P,) 0 right, 1 left
    leg: np.ndarray  # (P,) 0..5 for rods and sliders
    local: np.ndarray  # (P, 2, 3) endpoints: base frame (rails), platform frame (platform parts)
    radius: np.ndarray  # (P,)
    half_length: np.ndarray  # (P,) sliders: half their length
    pairs: np.ndarray  # (K, 2) checked per pose, closest-first at neutral
    pair_names: tuple[str, ...]
    platform_pairs: np.ndarray  # (M, 2) the pose-invariant platform–platform pairs


class PartArrays(NamedTuple):
    """What places every part, as one numba argument: the part table and the bases."""

    kind: np.ndarray  # (P,) PartKind
    robot: np.ndarray  # (P,)
    leg: np.ndarray  # (P,)
    local: np.ndarray  # (P, 2, 3)
    half_length: np.ndarray  # (P,)
    radius: np.ndarray  # (P,)
    rail_y: np.ndarray  # (2, 6)
    rail_z: float
    base_yaw: np.ndarray  # (2, 3, 3)
    base_origin: np.ndarray  # (2, 3)
    platform_joints: np.ndarray  # (2, 6, 3) B_i, platform frames


def _hexagon_order(joints: np.ndarray) -> np.ndarray:
    return np.argsort(np.arctan2(joints[:, 1], joints[:, 0]))


def _rail_label(robot_sliders: list[int]) -> str:
    return "/".join(str(leg + 1) for leg in robot_sliders)


def build_part_table(twin: TwinRobot) -> PartTable:
    parts = twin.parts
    names: list[str] = []
    kind: list[int] = []
    robot_index: list[int] = []
    legs: list[int] = []
    local: list[np.ndarray] = []
    radius: list[float] = []
    half: list[float] = []
    rail_of_leg: dict[tuple[int, int], int] = {}
    body: list[tuple[int, int, int]] = []  # (kind of body, robot, index): parts of one rigid body share it

    def add(name: str, part: PartKind, robot: int, leg: int, ends: np.ndarray, r: float, h: float = 0.0) -> int:
        names.append(name)
        kind.append(int(part))
        robot_index.append(robot)
        legs.append(leg)
        local.append(np.asarray(ends, dtype=float))
        radius.append(r)
        half.append(h)
        body.append((int(part) if part is not PartKind.PLATFORM else 3, robot, leg if part < 2 else 0))
        return len(names) - 1

    zeros = np.zeros((2, 3))
    for robot, side in enumerate(twin.sides):
        description = twin.robot_for(side)
        for leg in range(6):
            add(f"{side} rod {leg + 1}", PartKind.ROD, robot, leg, zeros, parts.rod_diameter_m / 2)
            add(
                f"{side} slider {leg + 1}",
                PartKind.SLIDER,
                robot,
                leg,
                zeros,
                parts.slider_diameter_m / 2,
                parts.slider_length_m / 2,
            )
        low = float(np.min(description.stroke_min_m)) - parts.rail_overhang_m
        high = float(np.max(description.stroke_max_m)) + parts.rail_overhang_m
        for rail_y in sorted(set(description.rail_y_m.tolist())):
            on_rail = [leg for leg in range(6) if description.rail_y_m[leg] == rail_y]
            index = add(
                f"{side} rail of sliders {_rail_label(on_rail)}",
                PartKind.RAIL,
                robot,
                -1,
                np.array([[low, rail_y, description.rail_z_m], [high, rail_y, description.rail_z_m]]),
                parts.rail_diameter_m / 2,
            )
            for leg in on_rail:
                rail_of_leg[(robot, leg)] = index
        joints = description.platform_joints_m
        order = _hexagon_order(joints)
        thickness = parts.platform_thickness_m
        for corner in range(6):
            a, b = order[corner], order[(corner + 1) % 6]
            add(f"{side} platform", PartKind.PLATFORM, robot, -1, np.stack([joints[a], joints[b]]), thickness / 2)
        foot = np.asarray(twin.placement(side).foot_plate_offset_m, dtype=float)
        plate_z = thickness / 2 + parts.foot_plate_thickness_m / 2
        add(
            f"{side} foot-plate arm",
            PartKind.PLATFORM,
            robot,
            -1,
            np.stack([np.zeros(3), foot + np.array([0.0, 0.0, plate_z])]),
            thickness / 2,
        )
        plate_radius = parts.foot_plate_thickness_m / 2
        half_length = max(parts.foot_plate_length_m / 2 - plate_radius, 0.0)
        edge = parts.foot_plate_width_m / 2 - plate_radius
        for offset in (-edge, edge):
            centre = foot + np.array([0.0, offset, plate_z])
            along = np.array([half_length, 0.0, 0.0])
            ends = np.stack([centre - along, centre + along])
            add(f"{side} foot plate", PartKind.PLATFORM, robot, -1, ends, plate_radius)

    count = len(names)
    pairs, platform_pairs = [], []
    for i in range(count):
        for j in range(i + 1, count):
            if body[i] == body[j] or (kind[i] == kind[j] == PartKind.RAIL):
                continue
            if _share_a_joint(i, j, kind, robot_index, legs, rail_of_leg):
                continue
            if kind[i] == kind[j] == PartKind.PLATFORM:
                platform_pairs.append((i, j))
            else:
                pairs.append((i, j))
    table = PartTable(
        names=tuple(names),
        kind=np.array(kind, dtype=np.int64),
        robot=np.array(robot_index, dtype=np.int64),
        leg=np.array(legs, dtype=np.int64),
        local=np.ascontiguousarray(local),
        radius=np.array(radius),
        half_length=np.array(half),
        pairs=np.array(pairs, dtype=np.int64).reshape(-1, 2),
        pair_names=(),
        platform_pairs=np.array(platform_pairs, dtype=np.int64).reshape(-1, 2),
    )
    return table


def _share_a_joint(
    i: int, j: int, kind: list[int], robot: list[int], leg: list[int], rail_of_leg: dict[tuple[int, int], int]
) -> bool:
    for a, b in ((i, j), (j, i)):
        if robot[a] != robot[b]:
            continue
        if kind[a] == PartKind.ROD:
            if kind[b] == PartKind.SLIDER and leg[a] == leg[b]:
                return True
            if kind[b] == PartKind.PLATFORM:
                return True
            if kind[b] == PartKind.RAIL and rail_of_leg[(robot[a], leg[a])] == b:
                return True
        if kind[a] == PartKind.SLIDER and kind[b] == PartKind.RAIL and rail_of_leg[(robot[a], leg[a])] == b:
            return True
    return False


# --- Kernels ------------------------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _clamp01(value: float) -> float:
    return min(1.0, max(0.0, value))


@numba.njit(cache=True, nogil=True)
def segment_distance(segment_a: np.ndarray, segment_b: np.ndarray) -> float:
    """Distance between two segments (2, 3) each (Ericson, Real-Time Collision Detection, §5.1.9)."""
    d1x = segment_a[1, 0] - segment_a[0, 0]
    d1y = segment_a[1, 1] - segment_a[0, 1]
    d1z = segment_a[1, 2] - segment_a[0, 2]
    d2x = segment_b[1, 0] - segment_b[0, 0]
    d2y = segment_b[1, 1] - segment_b[0, 1]
    d2z = segment_b[1, 2] - segment_b[0, 2]
    rx = segment_a[0, 0] - segment_b[0, 0]
    ry = segment_a[0, 1] - segment_b[0, 1]
    rz = segment_a[0, 2] - segment_b[0, 2]
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    tiny = 1e-18
    if a <= tiny and e <= tiny:
        s, t = 0.0, 0.0
    elif a <= tiny:
        s, t = 0.0, _clamp01(f / e)
    else:
        c = d1x * rx + d1y * ry + d1z * rz
        if e <= tiny:
            s, t = _clamp01(-c / a), 0.0
        else:
            b = d1x * d2x + d1y * d2y + d1z * d2z
            denominator = a * e - b * b
            s = _clamp01((b * f - c * e) / denominator) if denominator > tiny * a * e else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                s, t = _clamp01(-c / a), 0.0
            elif t > 1.0:
                s, t = _clamp01((b - c) / a), 1.0
    x = rx + d1x * s - d2x * t
    y = ry + d1y * s - d2y * t
    z = rz + d1z * s - d2z * t
    return math.sqrt(x * x + y * y + z * z)


@numba.njit(cache=True, nogil=True)
def twin_segments_into(
    parts: PartArrays,
    positions: np.ndarray,  # (2, 3) platform positions, base frames
    rotations: np.ndarray,  # (2, 3, 3)
    joints_world: np.ndarray,  # (2, 6, 3) platform joints p + R·B, base frames
    sliders: np.ndarray,  # (2, 6) slider x, base frames
    segments_out: np.ndarray,  # (P, 2, 3) world
) -> None:
    """Every part's segment in the world frame for one twin pose (scalars only: the tick allocates nothing)."""
    kind, robot, leg, local, half_length = parts.kind, parts.robot, parts.leg, parts.local, parts.half_length
    rail_y, rail_z, base_yaw, base_origin = parts.rail_y, parts.rail_z, parts.base_yaw, parts.base_origin
    for part in range(kind.shape[0]):
        side = robot[part]
        for end in range(2):
            if kind[part] == 0:  # ROD
                if end == 0:
                    x, y, z = sliders[side, leg[part]], rail_y[side, leg[part]], rail_z
                else:
                    joint = joints_world[side, leg[part]]
                    x, y, z = joint[0], joint[1], joint[2]
            elif kind[part] == 1:  # SLIDER
                offset = half_length[part] if end == 1 else -half_length[part]
                x, y, z = sliders[side, leg[part]] + offset, rail_y[side, leg[part]], rail_z
            elif kind[part] == 2:  # RAIL
                x, y, z = local[part, end, 0], local[part, end, 1], local[part, end, 2]
            else:  # PLATFORM
                rotation, point = rotations[side], local[part, end]
                x = positions[side, 0] + rotation[0, 0] * point[0]
                x, y = x + rotation[0, 1] * point[1], positions[side, 1] + rotation[1, 0] * point[0]
                x, y = x + rotation[0, 2] * point[2], y + rotation[1, 1] * point[1]
                y, z = y + rotation[1, 2] * point[2], positions[side, 2] + rotation[2, 0] * point[0]
                z = z + rotation[2, 1] * point[1] + rotation[2, 2] * point[2]
            yaw = base_yaw[side]
            for i in range(3):
                segments_out[part, end, i] = base_origin[side, i] + yaw[i, 0] * x + yaw[i, 1] * y + yaw[i, 2] * z


@numba.njit(cache=True, nogil=True)
def min_clearance_kernel(
    segments: np.ndarray, radius: np.ndarray, pairs: np.ndarray, boxes: np.ndarray, exact_below: float
) -> tuple[float, int]:
    """(smallest clearance, its pair index) over `pairs` for one pose's segments (P, 2, 3), exact where it
    is below `exact_below` (else `exact_below` and pair −1: nothing is that close). A pair is skipped only
    when its bounding boxes are already farther apart than the closest pair so far (or `exact_below`).
    `boxes` is (P, 6) scratch. NaN segments (a rod that cannot reach) are skipped."""
    for part in range(segments.shape[0]):
        for i in range(3):
            boxes[part, i] = min(segments[part, 0, i], segments[part, 1, i])
            boxes[part, 3 + i] = max(segments[part, 0, i], segments[part, 1, i])
    best = exact_below
    best_pair = -1
    for k in range(pairs.shape[0]):
        a, b = pairs[k, 0], pairs[k, 1]
        # The segments' boxes' gap bounds their distance from below, so the capsules' clearance too.
        gap = 0.0
        for i in range(3):
            gap = max(gap, boxes[b, i] - boxes[a, 3 + i], boxes[a, i] - boxes[b, 3 + i])
        if gap - radius[a] - radius[b] >= best:
            continue
        clearance = segment_distance(segments[a], segments[b]) - radius[a] - radius[b]
        if clearance < best:
            best = clearance
            best_pair = k
    return best, best_pair


@numba.njit(cache=True, nogil=True)
def _joints_world_into(parts: PartArrays, positions: np.ndarray, rotations: np.ndarray, out: np.ndarray) -> None:
    """The platform joints p + R·B of both robots (2, 6, 3), base frames, for one twin pose."""
    joints = parts.platform_joints
    for side in range(2):
        for leg in range(6):
            for i in range(3):
                lever = rotations[side, i, 0] * joints[side, leg, 0] + rotations[side, i, 1] * joints[side, leg, 1]
                out[side, leg, i] = positions[side, i] + (lever + rotations[side, i, 2] * joints[side, leg, 2])


@numba.njit(cache=True, nogil=True)
def _segments_into(
    parts: PartArrays, positions: np.ndarray, rotations: np.ndarray, sliders: np.ndarray, segments_out: np.ndarray
) -> None:
    joints = np.empty((2, 6, 3))
    for pose in range(positions.shape[0]):
        _joints_world_into(parts, positions[pose], rotations[pose], joints)
        twin_segments_into(parts, positions[pose], rotations[pose], joints, sliders[pose], segments_out[pose])


@numba.njit(cache=True, nogil=True)
def _swept_boxes_into(segments: np.ndarray, boxes: np.ndarray) -> None:
    """Each part's bounding box (P, 6: min xyz, max xyz) over a block of poses' segments (B, P, 2, 3). A NaN
    end (a rod that cannot reach) widens nothing: the narrow phase skips it too."""
    boxes[:, :3] = np.inf
    boxes[:, 3:] = -np.inf
    for pose in range(segments.shape[0]):
        for part in range(segments.shape[1]):
            for end in range(2):
                for i in range(3):
                    value = segments[pose, part, end, i]
                    if value < boxes[part, i]:
                        boxes[part, i] = value
                    if value > boxes[part, 3 + i]:
                        boxes[part, 3 + i] = value


@numba.njit(cache=True, nogil=True)
def _batch_clearance(
    parts: PartArrays,
    pairs: np.ndarray,
    positions: np.ndarray,  # (N, 2, 3)
    rotations: np.ndarray,  # (N, 2, 3, 3)
    sliders: np.ndarray,  # (N, 2, 6)
    all_pairs: bool,
    exact_below: float,
    clearance_out: np.ndarray,  # (N,)
    pair_out: np.ndarray,  # (N,)
    pair_clearance_out: np.ndarray,  # (N, K) when all_pairs
) -> None:
    """Per pose: every pair's clearance (`all_pairs`), or the smallest with `min_clearance_kernel`. Poses go in
    blocks of `BROAD_PHASE_POSES`: a pair whose parts' boxes, swept over the whole block, stay `exact_below`
    apart cannot come closer at any pose of it, so the narrow phase skips it (the minimum stays exact, and
    ties keep the first pair in `pairs`' order)."""
    radius = parts.radius
    part_count = parts.kind.shape[0]
    segments = np.empty((BROAD_PHASE_POSES, part_count, 2, 3))
    swept = np.empty((part_count, 6))
    boxes = np.empty((part_count, 6))
    candidates = np.empty(pairs.shape[0], dtype=np.int64)
    candidate_pairs = np.empty_like(pairs)
    for start in range(0, positions.shape[0], BROAD_PHASE_POSES):
        block = min(BROAD_PHASE_POSES, positions.shape[0] - start)
        stop = start + block
        _segments_into(parts, positions[start:stop], rotations[start:stop], sliders[start:stop], segments[:block])
        if all_pairs:
            for row in range(block):
                best, best_pair = np.inf, -1
                for k in range(pairs.shape[0]):
                    a, b = pairs[k, 0], pairs[k, 1]
                    value = segment_distance(segments[row, a], segments[row, b]) - radius[a] - radius[b]
                    pair_clearance_out[start + row, k] = value
                    if value < best:
                        best, best_pair = value, k
                clearance_out[start + row], pair_out[start + row] = best, best_pair
            continue
        _swept_boxes_into(segments[:block], swept)
        count = 0
        for k in range(pairs.shape[0]):
            a, b = pairs[k, 0], pairs[k, 1]
            gap = 0.0
            for i in range(3):
                gap = max(gap, swept[b, i] - swept[a, 3 + i], swept[a, i] - swept[b, 3 + i])
            if gap - radius[a] - radius[b] < exact_below:
                candidates[count] = k
                candidate_pairs[count, 0], candidate_pairs[count, 1] = a, b
                count += 1
        for row in range(block):
            best, best_pair = min_clearance_kernel(segments[row], radius, candidate_pairs[:count], boxes, exact_below)
            clearance_out[start + row] = best
            pair_out[start + row] = candidates[best_pair] if best_pair >= 0 else -1


# --- The model ------------------------------------------------------------------------------------------


class PoseInputs(NamedTuple):
    """Per twin pose (N, 2 robots, ...): platform positions and rotations (base frames) and the slider
    positions: what places every part."""

    positions: np.ndarray  # (N, 2, 3)
    rotations: np.ndarray  # (N, 2, 3, 3)
    sliders: np.ndarray  # (N, 2, 6)


@dataclass(frozen=True)
class ClearanceResult:
    clearance_m: np.ndarray  # (N,) smallest clearance between parts that share no joint
    closest_pair: np.ndarray  # (N,) index into `pair_names`
    pair_names: tuple[str, ...]
    clearance_min_m: float

    @property
    def colliding(self) -> np.ndarray:
        return ~(self.clearance_m >= self.clearance_min_m)

    def closest(self, pose_index: int) -> str:
        return self.pair_names[int(self.closest_pair[pose_index])]


class TwinClearance:
    """The twin's parts and the clearance between them; build once per twin (`twin_clearance`)."""

    def __init__(self, twin: TwinRobot) -> None:
        self.twin = twin
        table = build_part_table(twin)
        robots = [twin.robot_for(side) for side in twin.sides]
        self.rail_y = np.ascontiguousarray([r.rail_y_m for r in robots])
        self.rail_z = float(robots[0].rail_z_m)
        self.base_yaw = np.ascontiguousarray([yaw_matrix(twin.placement(s).base_yaw_rad) for s in twin.sides])
        self.base_origin = np.ascontiguousarray([twin.placement(s).base_origin_m for s in twin.sides], dtype=float)
        self.clearance_min_m = twin.parts.clearance_min_m
        self.table = table
        self.arrays = PartArrays(
            table.kind,
            table.robot,
            table.leg,
            table.local,
            table.half_length,
            table.radius,
            self.rail_y,
            self.rail_z,
            self.base_yaw,
            self.base_origin,
            np.ascontiguousarray([r.platform_joints_m for r in robots], dtype=float),
        )
        # Pairs that can come within IK_EXACT_BELOW_M of the margin first (a pose-independent bound says
        # which), then closest first at neutral, so that the running minimum prunes the rest early.
        neutral = self._inputs(np.zeros((1, 6)))
        all_clearances = self._pair_clearances(table.pairs, neutral)[0]
        bound = self._static_bounds(table)
        far = bound >= self.clearance_min_m + IK_EXACT_BELOW_M
        order = np.lexsort((all_clearances, far))
        pairs = np.ascontiguousarray(table.pairs[order])
        self.near_pair_count = int(np.count_nonzero(~far))
        self.table = replace(
            table, pairs=pairs, pair_names=tuple(f"{table.names[a]} – {table.names[b]}" for a, b in pairs)
        )
        # Pose-invariant: both platforms move with the stance frame as one rigid body.
        platform = self._pair_clearances(table.platform_pairs, neutral)[0]
        closest = int(np.argmin(platform))
        a, b = table.platform_pairs[closest]
        self.platform_clearance_m = float(platform[closest])
        self.platform_pair_name = f"{table.names[a]} – {table.names[b]}"

    def _static_bounds(self, table: PartTable) -> np.ndarray:
        """A lower bound on each pair's clearance at any pose: rails and sliders lie on their rail's
        axis, a rod within one rod length of its rail's axis; platform parts are not bounded (−inf)."""
        points, directions, reach = [], [], []
        rod_length = [self.twin.robot_for(side).rod_length_m for side in self.twin.sides]
        for part in range(len(table.names)):
            side, leg, kind = int(table.robot[part]), int(table.leg[part]), PartKind(int(table.kind[part]))
            rail_y = table.local[part, 0, 1] if kind is PartKind.RAIL else self.rail_y[side, max(leg, 0)]
            points.append(self.base_origin[side] + self.base_yaw[side] @ np.array([0.0, rail_y, self.rail_z]))
            directions.append(self.base_yaw[side] @ np.array([1.0, 0.0, 0.0]))
            reach.append({PartKind.ROD: rod_length[side], PartKind.PLATFORM: np.inf}.get(kind, 0.0))
        bounds = np.empty(len(table.pairs))
        for k, (a, b) in enumerate(table.pairs):
            normal = np.cross(directions[a], directions[b])
            offset = points[b] - points[a]
            if np.linalg.norm(normal) < 1e-9:  # parallel axes
                axis_distance = float(np.linalg.norm(np.cross(offset, directions[a])))
            else:
                axis_distance = abs(float(offset @ normal)) / float(np.linalg.norm(normal))
            bounds[k] = axis_distance - reach[a] - reach[b] - table.radius[a] - table.radius[b]
        return bounds

    def _inputs(self, stance_poses: np.ndarray) -> PoseInputs:
        platform = twin_platform_poses(self.twin, stance_poses)
        solutions = twin_inverse_kinematics(self.twin, stance_poses, check=False, clearance_check=False)
        return self.inputs_from(platform, solutions)

    def inputs_from(
        self, platform_poses: dict[str, tuple[np.ndarray, np.ndarray]], solutions: dict[str, IKSolution]
    ) -> PoseInputs:
        sides = self.twin.sides
        positions = np.ascontiguousarray(np.stack([platform_poses[s][0] for s in sides], axis=1), dtype=float)
        rotations = np.ascontiguousarray(np.stack([platform_poses[s][1] for s in sides], axis=1), dtype=float)
        sliders = np.ascontiguousarray(np.stack([solutions[s].slider_positions_m for s in sides], axis=1))
        return PoseInputs(positions, rotations, sliders)

    def _run(
        self, pairs: np.ndarray, all_pairs: bool, inputs: PoseInputs, exact_below: float = np.inf
    ) -> tuple[np.ndarray, ...]:
        count = len(inputs.positions)
        clearance = np.empty(count)
        closest = np.empty(count, dtype=np.int64)
        per_pair = np.empty((count if all_pairs else 0, len(pairs)))
        pairs = np.ascontiguousarray(pairs)

        def run_chunk(chunk: slice) -> None:
            _batch_clearance(
                self.arrays,
                pairs,
                inputs.positions[chunk],
                inputs.rotations[chunk],
                inputs.sliders[chunk],
                all_pairs,
                exact_below,
                clearance[chunk],
                closest[chunk],
                per_pair[chunk],
            )

        for_each_chunk(count, run_chunk)
        return clearance, closest, per_pair

    def _pair_clearances(self, pairs: np.ndarray, inputs: PoseInputs) -> np.ndarray:
        return self._run(pairs, True, inputs)[2]

    def from_solutions(
        self,
        platform_poses: dict[str, tuple[np.ndarray, np.ndarray]],
        solutions: dict[str, IKSolution],
        *,
        exact_below_m: float = np.inf,
    ) -> ClearanceResult:
        """Smallest clearance per pose from the twin IK's own results (no second IK). It is exact where it
        is below `exact_below_m`; elsewhere it is that bound (pair name `NOTHING_CLOSER`), which is faster."""
        inputs = self.inputs_from(platform_poses, solutions)
        # Pairs that can never come that close need no look (`_static_bounds`).
        near = exact_below_m <= self.clearance_min_m + IK_EXACT_BELOW_M
        pairs = self.table.pairs[: self.near_pair_count] if near else self.table.pairs
        clearance, closest, _ = self._run(pairs, False, inputs, exact_below_m)
        return self._result(clearance, closest)

    def _result(self, clearance: np.ndarray, closest: np.ndarray) -> ClearanceResult:
        # The pose-invariant platform pair joins the per-pose minimum; "nothing closer" is the last name.
        names = (*self.table.pair_names, self.platform_pair_name, NOTHING_CLOSER)
        closest = np.where(closest < 0, len(names) - 1, closest)
        platform_closer = self.platform_clearance_m < clearance
        clearance = np.where(platform_closer, self.platform_clearance_m, clearance)
        closest = np.where(platform_closer, len(names) - 2, closest)
        return ClearanceResult(clearance, closest, names, self.clearance_min_m)

    def clearance(self, stance_poses: np.ndarray) -> ClearanceResult:
        """Smallest clearance (m) per stance pose (N, 6) and the pair of parts it is between."""
        clearance, closest, _ = self._run(self.table.pairs, False, self._inputs(stance_poses))
        return self._result(clearance, closest)

    def pair_clearances(self, stance_poses: np.ndarray) -> np.ndarray:
        """Clearance (m) of every per-pose pair, (N, K) in `table.pair_names` order (no pruning)."""
        return self._pair_clearances(self.table.pairs, self._inputs(stance_poses))

    def segments(self, stance_poses: np.ndarray) -> np.ndarray:
        """Every part's segment in the world frame, (N, P, 2, 3); radii in `table.radius`."""
        inputs = self._inputs(stance_poses)
        out = np.empty((len(inputs.positions), len(self.table.names), 2, 3))
        _segments_into(self.arrays, inputs.positions, inputs.rotations, inputs.sliders, out)
        return out


@functools.lru_cache(maxsize=16)
def twin_clearance(twin: TwinRobot) -> TwinClearance:
    return TwinClearance(twin)


def min_clearance(twin: TwinRobot, stance_poses: np.ndarray) -> ClearanceResult:
    """Smallest clearance between the twin's parts (m) per stance pose (N, 6), with the pair's name."""
    return twin_clearance(twin).clearance(stance_poses)


def flag_collisions(
    twin: TwinRobot,
    platform_poses: dict[str, tuple[np.ndarray, np.ndarray]],
    solutions: dict[str, IKSolution],
) -> dict[str, IKSolution]:
    """The twin IK's solutions with COLLISION set on every leg of both robots where parts collide."""
    model = twin_clearance(twin)
    result = model.from_solutions(platform_poses, solutions, exact_below_m=model.clearance_min_m + IK_EXACT_BELOW_M)
    collisions = PoseCollisions(result.clearance_m, result.closest_pair, result.pair_names, result.clearance_min_m)
    flagged = {}
    colliding = result.colliding & np.isfinite(result.clearance_m)
    for side, solution in solutions.items():
        violations = solution.violations.copy()
        violations[colliding] |= np.uint8(LegViolation.COLLISION)
        flagged[side] = replace(solution, violations=violations, collisions=collisions)
    return flagged
