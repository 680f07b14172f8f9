"""`ssp-rehab ik` and `ssp-rehab fk`: one robot's kinematics, in mm and degrees at this edge."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from core.errors import InvalidValueError
from server.cli.output import console, emit, fail
from server.cli.robot_option import ROBOT_OPTION, twin_from_option

if TYPE_CHECKING:  # numpy and the kinematics (numba) load when a command runs, not for `--help`
    import numpy as np

    from core.robot import TwinRobot


def pose_si_from_mm_deg(pose_mm_deg: list[float]) -> np.ndarray:
    import numpy as np

    x, y, z, roll, pitch, yaw = pose_mm_deg
    return np.array([x / 1e3, y / 1e3, z / 1e3, math.radians(roll), math.radians(pitch), math.radians(yaw)])


def pose_mm_deg_from_si(pose: np.ndarray) -> list[float]:
    return [*(float(v) * 1e3 for v in pose[:3]), *(math.degrees(float(v)) for v in pose[3:])]


def register(app: typer.Typer) -> None:
    @app.command()
    def ik(
        pose: tuple[float, float, float, float, float, float] = typer.Option(
            ..., "--pose", help="X Y Z (mm) ROLL PITCH YAW (deg)", metavar="X Y Z ROLL PITCH YAW"
        ),
        as_json: bool = typer.Option(False, "--json"),
        twin_pose: bool = typer.Option(
            False, "--twin", help="POSE is a stance pose relative to neutral; solve both robots (world frame)."
        ),
        robot_file: Path | None = ROBOT_OPTION,
    ) -> None:
        """Slider positions (mm along each rail, REFERENCE.md order) for one platform pose, or with
        --twin both robots' sliders and rod ends (world frame, mm) for one stance pose."""
        if twin_pose:
            _twin_ik(pose, as_json, robot_file)
            return
        import numpy as np

        from core.kinematics import UnreachablePoseError, inverse_kinematics

        try:
            robot = twin_from_option(robot_file).robot
            solution = inverse_kinematics(robot, pose_si_from_mm_deg(list(pose)))
        except (UnreachablePoseError, InvalidValueError, ValueError) as error:
            raise fail(str(error), as_json=as_json) from error
        data: dict[str, Any] = {
            "pose": {
                "x_mm": pose[0],
                "y_mm": pose[1],
                "z_mm": pose[2],
                "roll_deg": pose[3],
                "pitch_deg": pose[4],
                "yaw_deg": pose[5],
            },
            "sliders_mm": (solution.slider_positions_m[0] * 1e3).tolist(),
            "base_cone_deg": np.degrees(solution.base_cone_rad[0]).tolist(),
            "platform_cone_deg": np.degrees(solution.platform_cone_rad[0]).tolist(),
        }

        def human(d: dict[str, Any]) -> None:
            for index, value in enumerate(d["sliders_mm"], start=1):
                console.print(f"slider {index}: {value:10.2f} mm")

        emit(data, as_json=as_json, human=human)

    @app.command()
    def fk(
        sliders: tuple[float, float, float, float, float, float] = typer.Option(
            ..., "--sliders", help="six slider positions (mm)", metavar="S1 S2 S3 S4 S5 S6"
        ),
        as_json: bool = typer.Option(False, "--json"),
        robot_file: Path | None = ROBOT_OPTION,
    ) -> None:
        """Platform pose (mm, deg) for six slider positions, by Newton from the neutral pose."""
        import numpy as np

        from core.kinematics import ForwardKinematics, ForwardKinematicsError

        try:
            robot = twin_from_option(robot_file).robot
            result = ForwardKinematics(robot).solve(np.asarray(sliders) / 1e3)
        except (ForwardKinematicsError, InvalidValueError, ValueError) as error:
            raise fail(str(error), as_json=as_json) from error
        pose = pose_mm_deg_from_si(result.pose)
        data = {
            "pose": dict(zip(["x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"], pose, strict=True)),
            "iterations": result.iterations,
            "residual_mm": result.residual_m * 1e3,
        }

        def human(d: dict[str, Any]) -> None:
            for key, value in d["pose"].items():
                console.print(f"{key:>9}: {value:12.6f}")
            console.print(f"{d['iterations']} iterations, residual {d['residual_mm']:.3g} mm")

        emit(data, as_json=as_json, human=human)


def twin_ik_report(twin: TwinRobot, stance_pose: np.ndarray) -> dict[str, Any]:
    """Both robots at one stance pose, world frame, mm: sliders, rod ends, foot plates, every violation."""
    import numpy as np

    from core.kinematics import platform_joints_world, twin_inverse_kinematics, twin_platform_poses, yaw_matrix

    solutions = twin_inverse_kinematics(twin, stance_pose[None, :], check=False)
    platforms = twin_platform_poses(twin, stance_pose[None, :])
    robots: dict[str, Any] = {}
    feet = []
    for side in twin.sides:
        placement, robot = twin.placement(side), twin.robot_for(side)
        yaw, origin = yaw_matrix(placement.base_yaw_rad), np.asarray(placement.base_origin_m)
        positions, rotations = platforms[side]
        sliders = solutions[side].slider_positions_m[0]
        slider_joints = np.column_stack([sliders, robot.rail_y_m, np.full(6, robot.rail_z_m)])
        platform_joints = platform_joints_world(robot, positions, rotations)[0]
        foot = positions[0] + rotations[0] @ np.asarray(placement.foot_plate_offset_m)
        robots[side] = {
            "sliders_mm": (sliders * 1e3).tolist(),
            "slider_joints_mm": ((origin + slider_joints @ yaw.T) * 1e3).tolist(),
            "platform_joints_mm": ((origin + platform_joints @ yaw.T) * 1e3).tolist(),
        }
        feet.append(((origin + yaw @ foot) * 1e3).tolist())
    violations = [
        {"robot": side, "reason": v.reason, "slider": v.slider, "value": v.value, "limit": v.limit, "unit": v.unit}
        for side, solution in solutions.items()
        for v in solution.limit_violations()
    ]
    return {
        "stance_pose": dict(zip(POSE_KEYS, pose_mm_deg_from_si(stance_pose), strict=True)),
        "reachable": not violations,
        "violations": violations,
        "robots": robots,
        "foot_plates_mm": feet,
    }


POSE_KEYS = ["x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg"]


def _twin_ik(pose: tuple[float, ...], as_json: bool, robot_file: Path | None) -> None:
    try:
        data = twin_ik_report(twin_from_option(robot_file), pose_si_from_mm_deg(list(pose)))
    except (InvalidValueError, ValueError) as error:
        raise fail(str(error), as_json=as_json) from error

    def human(d: dict[str, Any]) -> None:
        for side, robot in d["robots"].items():
            sliders = "  ".join(f"{value:9.2f}" for value in robot["sliders_mm"])
            console.print(f"{side:>5} sliders (mm): {sliders}")
        for violation in d["violations"]:
            unit = f" {violation['unit']}" if violation["unit"] else ""
            console.print(
                f"{violation['robot']} robot: {violation['reason']} "
                f"(value {violation['value']:.6g}{unit}, limit {violation['limit']:.6g}{unit})"
            )
        console.print("reachable" if d["reachable"] else "NOT reachable")

    emit(data, as_json=as_json, human=human)
    if not data["reachable"]:
        raise typer.Exit(1)
