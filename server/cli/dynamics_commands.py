"""`ssp-rehab dynamics --scenario paper-z|paper-y`: the paper's dynamics simulations (§3.2.1–3.2.2), with the
inverse dynamics of core.dynamics cross-checked against MuJoCo's, and plots like Figures 10–11.

The paper gives no masses. Its setting is taken as the rated load (§3.3.1: 250 kg at the platform centre) on
each robot; `--setting patient` runs the twin with a patient of given mass and height instead."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

    from core.dynamics import (
        PayloadModel,
        StanceTrajectory,
    )
    from core.robot import SSPRobot, TwinRobot

import typer

from core.errors import InvalidValueError
from server.cli.output import console, emit, fail, progress_bar, pyplot, save_figure
from server.cli.robot_option import ROBOT_OPTION, twin_from_option

SCENARIOS = {"paper-z": "z", "paper-y": "y"}
SAMPLE_PERIOD_S = 0.001
CROSS_CHECK_PERIOD_S = 0.005  # MuJoCo's inverse runs in Python per sample: every 5th ms is plenty
BAND_SCAN_STEP_KG, BAND_SCAN_LIMIT_KG = 10.0, 2000.0


SETTINGS = ("rated-load", "patient")


def paper_setting(twin: TwinRobot) -> tuple[TwinRobot, PayloadModel]:
    """The paper's setting (§3.2, §3.3.1): each robot carries the rated load, a compact 250 kg mass at its
    platform centre. Expressed on the twin by putting each foot plate at its platform centre, so that one
    rigid payload of twice the rated load splits into the rated load on each robot."""
    from core.dynamics import PayloadModel

    centred = dataclasses.replace(
        twin,
        right=dataclasses.replace(twin.right, foot_plate_offset_m=(0.0, 0.0, 0.0)),
        left=dataclasses.replace(twin.left, foot_plate_offset_m=(0.0, 0.0, 0.0)),
    )
    rated_kg = twin.robot.mass.rated_payload_kg
    # A compact load: a uniform 0.4 m cube (I = m·a²/6) centred on the platform; MuJoCo needs some inertia.
    cube_inertia = 2.0 * rated_kg * 0.4**2 / 6.0
    return centred, PayloadModel(mass_kg=2.0 * rated_kg, inertia_kg_m2=(cube_inertia,) * 3)


def mass_assumptions(twin: TwinRobot, payload: PayloadModel, include_rods: bool, setting: str) -> dict[str, Any]:
    mass = twin.robot.mass
    load = (
        {"payload": payload.scaled(0.5).to_dict(), "payload_placement": "compact 0.4 m cube at each platform centre"}
        if setting == "rated-load"
        else {"patient": payload.to_dict(), "patient_split": "half of the body on each foot plate, above that foot"}
    )
    return {
        "note": "the paper gives no masses; these are stated assumptions (core.robot.MassProperties)",
        "platform_mass_kg": mass.platform_mass_kg,
        "platform_inertia_kg_m2": list(mass.platform_inertia_kg_m2),
        "slider_mass_kg": mass.slider_mass_kg,
        "rod_mass_kg": mass.rod_mass_kg if include_rods else 0.0,
        **load,
        "friction": "neglected, as in the paper",
    }


def band_payload_scan(robot: SSPRobot, trajectory: StanceTrajectory) -> dict[str, Any]:
    """Which compact payloads on one robot's platform centre put every joint's peak force in the band."""
    import numpy as np

    from core.dynamics import InverseDynamics, PayloadModel, force_summary

    masses_kg = np.arange(0.0, BAND_SCAN_LIMIT_KG + BAND_SCAN_STEP_KG / 2, BAND_SCAN_STEP_KG)
    scan_limit = dataclasses.replace(robot.mass, rated_payload_kg=BAND_SCAN_LIMIT_KG)
    unrated = dataclasses.replace(robot, mass=scan_limit)
    poses = trajectory.poses + np.asarray(robot.neutral_pose)
    in_band = [
        float(mass_kg)
        for mass_kg in masses_kg
        if force_summary(
            InverseDynamics(unrated, PayloadModel(float(mass_kg))).slider_forces(
                poses, trajectory.velocities, trajectory.accelerations
            )
        )["in_paper_band"]
    ]
    return {
        "single_robot_payload_in_band_kg": [min(in_band), max(in_band)] if in_band else None,
        "scanned_kg": [float(masses_kg[0]), float(masses_kg[-1])],
    }


def run_scenario(
    twin: TwinRobot,
    scenario: str,
    duration_s: float,
    payload: PayloadModel,
    *,
    setting: str,
    include_rods: bool,
    progress: bool,
) -> tuple[dict[str, Any], StanceTrajectory, np.ndarray]:
    import numpy as np

    from core.dynamics import (
        PAPER_ACCELERATION_AFTER_M_S2,
        PAPER_ACCELERATION_BEFORE_M_S2,
        PAPER_STEP_TIME_S,
        StanceTrajectory,
        TwinInverseDynamics,
        force_summary,
        paper_step_trajectory,
    )
    from core.kinematics import twin_inverse_kinematics
    from server.hal.sim.mjcf import SimModelOptions
    from server.hal.sim.model import TwinSimModel, rms_relative_error

    if setting == "rated-load":
        twin, payload = paper_setting(twin)
    trajectory = paper_step_trajectory(SCENARIOS[scenario], duration_s, SAMPLE_PERIOD_S)
    twin_inverse_kinematics(twin, trajectory.poses)  # refuses a trajectory that leaves the workspace
    dynamics = TwinInverseDynamics(twin, payload, include_rods=include_rods)
    forces = dynamics.slider_forces(trajectory.poses, trajectory.velocities, trajectory.accelerations)
    stride = round(CROSS_CHECK_PERIOD_S / SAMPLE_PERIOD_S)
    sparse = StanceTrajectory(*(getattr(trajectory, f.name)[::stride] for f in dataclasses.fields(trajectory)))
    with progress_bar("MuJoCo cross-check", 2, enabled=progress) as advance:
        model = TwinSimModel(twin, SimModelOptions(payload=payload, include_rods=include_rods))
        advance(1)
        mujoco_result = model.inverse_slider_forces(dynamics, sparse)
        advance(1)
    summary = force_summary(forces)
    data: dict[str, Any] = {
        "scenario": scenario,
        "setting": setting,
        "direction": f"+{SCENARIOS[scenario].upper()}",
        "acceleration_m_s2": {
            "before": PAPER_ACCELERATION_BEFORE_M_S2,
            "after": PAPER_ACCELERATION_AFTER_M_S2,
            "step_time_s": PAPER_STEP_TIME_S,
        },
        "duration_s": duration_s,
        "sample_period_s": SAMPLE_PERIOD_S,
        "initial_pose": "neutral (platforms at z = 600 mm), at rest",
        "band_criterion": "each joint's peak |force| over the motion (what its drive must deliver)",
        **summary,
        "mujoco_rms_rel_error": rms_relative_error(forces[::stride], mujoco_result.slider_forces_n),
        "mujoco_max_equation_residual": mujoco_result.max_residual,
        "per_slider_peak_abs_n": {
            f"{side} {i + 1}": float(np.abs(forces[:, 6 * k + i]).max())
            for k, side in enumerate(twin.sides)
            for i in range(6)
        },
        "forces_at_end_n": forces[-1].tolist(),
        "mass_assumptions": mass_assumptions(twin, payload, include_rods, setting),
        "band_check": band_payload_scan(twin.robot, trajectory),
    }
    return data, trajectory, forces


def plot_scenario(directory: Path, scenario: str, trajectory: StanceTrajectory, forces: np.ndarray) -> list[Path]:
    from core.dynamics import PAPER_FORCE_BAND_N

    plt = pyplot()
    figure, axes = plt.subplots(3, 1, figsize=(8, 9), sharex=True)
    axis_index = "xyz".index(SCENARIOS[scenario])
    axes[0].plot(trajectory.times_s, trajectory.accelerations[:, axis_index])
    axes[0].set_ylabel("acceleration (m/s²)")
    axes[0].set_title(f"{scenario}: acceleration step along +{SCENARIOS[scenario].upper()} (paper Fig. 9)")
    for row, side in ((1, "right"), (2, "left")):
        offset = 0 if side == "right" else 6
        for slider in range(6):
            axes[row].plot(trajectory.times_s, forces[:, offset + slider], label=f"slider {slider + 1}")
        low, high = PAPER_FORCE_BAND_N
        for bound in (low, high, -low, -high):
            axes[row].axhline(bound, color="grey", linewidth=0.6, linestyle=":")
        axes[row].set_ylabel(f"{side} robot force (N)")
        axes[row].legend(ncol=3, fontsize=8)
    axes[2].set_xlabel("time (s)")
    return [save_figure(figure, directory, f"dynamics_{scenario}")]


def register(app: typer.Typer) -> None:
    @app.command()
    def dynamics(
        scenario: str = typer.Option(..., "--scenario", help="paper-z or paper-y (paper §3.2.1, §3.2.2)"),
        duration_s: float = typer.Option(0.3, "--duration", help="simulated time (s)"),
        setting: str = typer.Option(
            "rated-load", "--setting", help="rated-load: 250 kg at each platform centre (the paper's); patient"
        ),
        body_mass_kg: float = typer.Option(75.0, "--body-mass", help="patient body mass (kg), with --setting patient"),
        height_m: float = typer.Option(1.75, "--height", help="patient height (m)"),
        neglect_rods: bool = typer.Option(False, "--neglect-rods", help="rods massless"),
        as_json: bool = typer.Option(False, "--json"),
        plot: Path | None = typer.Option(None, "--plot", help="directory for PNG plots (like Figures 10–11)"),
        robot_file: Path | None = ROBOT_OPTION,
    ) -> None:
        """Slider drive forces for the paper's acceleration step (5 → 0.5 m/s² at 0.1 s), checked against MuJoCo."""
        from core.dynamics import DynamicsError, PayloadModel
        from core.kinematics import UnreachablePoseError

        if scenario not in SCENARIOS:
            raise fail(f"scenario = {scenario!r}: must be one of {sorted(SCENARIOS)}", as_json=as_json)
        if setting not in SETTINGS:
            raise fail(f"setting = {setting!r}: must be one of {list(SETTINGS)}", as_json=as_json)
        if not 0.1 < duration_s <= 1.0:
            raise fail(f"duration = {duration_s}: must be in (0.1, 1.0] s", as_json=as_json)
        try:
            twin = twin_from_option(robot_file)
            payload = PayloadModel.from_body(body_mass_kg, height_m)
            data, trajectory, forces = run_scenario(
                twin,
                scenario,
                duration_s,
                payload,
                setting=setting,
                include_rods=not neglect_rods,
                progress=not as_json,
            )
        except (InvalidValueError, UnreachablePoseError, DynamicsError, ValueError) as error:
            raise fail(str(error), as_json=as_json) from error
        if plot is not None:
            data["plots"] = [str(p) for p in plot_scenario(plot, scenario, trajectory, forces)]
        emit(data, as_json=as_json, human=_print_human)


def _print_human(data: dict[str, Any]) -> None:
    console.print(
        f"[bold]{data['scenario']}[/]: {data['acceleration_m_s2']['before']} → {data['acceleration_m_s2']['after']} "
        f"m/s² at {data['acceleration_m_s2']['step_time_s']} s along {data['direction']}, "
        f"{data['duration_s']} s from the neutral pose at rest, setting {data['setting']}"
    )
    for name, value in data["per_slider_peak_abs_n"].items():
        console.print(f"  {name:>9}: peak |F| {value:8.1f} N")
    low, high = data["paper_band_n"]
    verdict = "inside" if data["in_paper_band"] else "NOT inside"
    console.print(
        f"peak |F| per joint from {data['min_abs_force_n']:.1f} to {data['max_abs_force_n']:.1f} N: {verdict} "
        "the paper's "
        f"{low:.0f}–{high:.0f} N band"
    )
    band = data["band_check"]["single_robot_payload_in_band_kg"]
    console.print(
        "  one robot with a compact payload at its platform centre lands in the band for "
        + (f"{band[0]:.0f}–{band[1]:.0f} kg" if band else "no payload in the scanned range")
    )
    console.print(f"MuJoCo cross-check: RMS relative error {data['mujoco_rms_rel_error']:.2e}")
    masses = data["mass_assumptions"]
    load = masses.get("payload") or masses["patient"]
    console.print(
        f"masses (assumed): platform {masses['platform_mass_kg']} kg, slider {masses['slider_mass_kg']} kg, "
        f"rod {masses['rod_mass_kg']} kg, load {load['mass_kg']} kg per robot"
        + ("" if "payload" in masses else " (the patient, shared by both robots)")
    )
    for path in data.get("plots", []):
        console.print(f"plot: {path}")
