"""`ssp-rehab cueing plan|compare`: classical washout against optimal cueing (issue 14 §5), judged at the
patient's head on the default twin, each plan checked by the worker's own offline check.

Figures (SI in the JSON keys):
- `feasible`, `reason`: the worker's offline check (`check_plan`); the reason names the first limit, the
  segment, the time and the value, and is null when feasible;
- `perceived_specific_force_error_rms_m_s2`: RMS over the whole timeline (return ramps included) of the
  norm over the three axes of otolith(delivered at the head) − otolith(cue as played: soft start, fade out);
- `perceived_specific_force_error_rms_raw_m_s2`: the same against the cue as written (`raw_cue`);
- `perceived_angular_velocity_error_rms_rad_s`: the same through the canals;
- `peak_tilt_rate_rad_s`: the largest roll or pitch rate of the platform that the cue does not ask for;
- `max_condition_number`: of either robot's Jacobian; `max_stroke_use_fraction`: the largest slider
  excursion from neutral over the room to that side's stroke end;
- `min_clearance_mm`: the smallest clearance between the twin's parts (`core.clearance`) over the timeline.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

    from core.plan.build import PrescriptionPlan
    from core.robot import TwinRobot

import typer

from core.errors import InvalidValueError
from core.physics import GRAVITY_M_S2
from server.cli.output import console, emit, fail, progress_bar, pyplot, save_figure
from server.cli.robot_option import ROBOT_OPTION, twin_from_option

# The comparison suite: the paper's two scenarios and three clinical ones (issue 14 §5).
SUITE: dict[str, dict[str, Any]] = {
    "paper-square-wave": {  # §4.2 tuning input: ±2 m/s² along x, period 2 s, 10 s
        "segments": [
            {"cue": {"kind": "square_wave", "axis": "x", "amplitude_m_s2": 2.0, "period_s": 2.0}, "duration_s": 10.0}
        ]
    },
    "paper-tilt-step": {  # §5: 0.2 g along +y for 10 s, then 0
        "segments": [
            {
                "cue": {"kind": "step", "axis": "y", "final_m_s2": 0.2 * GRAVITY_M_S2, "end_time_s": 10.0},
                "duration_s": 20.0,
            }
        ]
    },
    "gait": {
        "segments": [
            {
                "cue": {
                    "kind": "gait",
                    "cadence_steps_per_min": 100.0,
                    "vertical_amplitude_m_s2": 0.6,
                    "forward_amplitude_m_s2": 0.4,
                    "lateral_amplitude_m_s2": 0.3,
                },
                "duration_s": 15.0,
            }
        ]
    },
    "perturbations": {
        "seed": 7,
        "segments": [
            {
                "cue": {
                    "kind": "perturbations",
                    "translation_m_s2": 1.5,
                    "tilt_rate_rad_s": 0.1,
                    "pulse_duration_s": 0.5,
                    "interval_min_s": 3.0,
                    "interval_max_s": 5.0,
                    "first_onset_s": 1.5,
                },
                "duration_s": 15.0,
            }
        ],
    },
    "sine-sway": {
        "segments": [
            {"cue": {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.25}, "duration_s": 12.0}
        ]
    },
}


def _clearance_m(twin: TwinRobot, poses: np.ndarray) -> np.ndarray:
    """Smallest collision clearance (N,) m between the twin's parts (`core.clearance`)."""
    from core.clearance import min_clearance

    return min_clearance(twin, poses).clearance_m


def _condition_numbers(twin: TwinRobot, poses: np.ndarray) -> np.ndarray:
    """(N, 2) condition number of each robot's Jacobian; NaN where a rod cannot reach its rail."""
    import numpy as np

    from core.kinematics import condition_number, euler_from_rotation, twin_inverse_kinematics, twin_platform_poses

    solutions = twin_inverse_kinematics(twin, poses, check=False)
    result = np.full((len(poses), 2), np.nan)
    for index, (side, (positions, rotations)) in enumerate(twin_platform_poses(twin, poses).items()):
        reachable = np.all(np.isfinite(solutions[side].slider_positions_m), axis=1)
        robot_poses = np.concatenate([positions, euler_from_rotation(rotations)], axis=1)
        result[reachable, index] = condition_number(twin.robot_for(side), robot_poses[reachable])
    return result


def _stroke_use(twin: TwinRobot, poses: np.ndarray) -> np.ndarray:
    """(N,) largest slider excursion from neutral over the room to the stroke end on that side."""
    import numpy as np

    from core.kinematics import twin_inverse_kinematics

    solutions = twin_inverse_kinematics(twin, np.concatenate([np.zeros((1, 6)), poses]), check=False)
    sliders = np.concatenate([solutions[side].slider_positions_m for side in twin.sides], axis=1)
    robots = [twin.robot_for(side) for side in twin.sides]
    low = np.concatenate([r.stroke_min_m for r in robots])
    high = np.concatenate([r.stroke_max_m for r in robots])
    neutral, moved = sliders[0], sliders[1:] - sliders[0]
    room = np.where(moved >= 0.0, high - neutral, neutral - low)
    return np.max(np.abs(moved) / room, axis=1)


def raw_cue(plan: PrescriptionPlan, samples: int) -> np.ndarray:
    """The prescribed specific force (samples, 3) as written: each segment's cue over its duration, without the
    soft start, zero after it (fade out and return to neutral), segments end to end as the timeline plays them."""
    import numpy as np

    from core.cues import cue_from_spec
    from core.plan.timeline import segment_timelines

    period = plan.sample_period_s
    force, start = np.zeros((samples, 3)), 0
    for part in segment_timelines(plan):
        segment = part.segment
        written, _ = cue_from_spec(segment.cue_spec, period, segment.seed).generate(segment.cue_samples * period)
        length = min(round(segment.duration_s / period), len(written))
        force[start : start + length] = written[:length]
        start += len(part.poses)
    return force


def evaluate(prescription: dict[str, Any], twin: TwinRobot, cueing: str, patient: dict[str, Any] | None = None) -> dict:
    """Plan (timed), check and judge one prescription with one algorithm; `_series` holds the curves."""
    import numpy as np

    from core.perception import DEFAULT_HEAD_HEIGHT_M, head_height_m
    from core.plan.build import plan_prescription
    from core.plan.check import check_plan
    from core.plan.prescription import PrescriptionError
    from core.plan.rejection import PrescriptionRejected
    from core.plan.timeline import prescription_timeline
    from core.vestibular import PerceptionThresholds, VestibularModel
    from server.prescriptions.preview import perceived_at_head

    # The body of POST /api/v1/prescriptions: its patient and note do not shape the plan; anything else is
    # validated by the one prescription model (an unknown key is refused, not dropped).
    if not isinstance(prescription, dict):
        raise PrescriptionError("prescription", type(prescription).__name__, "must be an object with 'segments'")
    body = {key: value for key, value in prescription.items() if key not in ("patient_id", "note")}
    started, cpu_started = time.perf_counter(), time.process_time()
    plan: PrescriptionPlan = plan_prescription({**body, "cueing": cueing}, twin, patient=patient)
    planning_wall_s, planning_cpu_s = time.perf_counter() - started, time.process_time() - cpu_started
    try:
        check_plan(plan, twin)
        feasible, reason = True, None
    except PrescriptionRejected as rejection:
        feasible, reason = False, str(rejection)
    period = plan.sample_period_s
    timeline = prescription_timeline(plan)
    head_m = head_height_m(patient["height_m"]) if patient else DEFAULT_HEAD_HEIGHT_M
    perceived = perceived_at_head(timeline, period, head_m)
    force_error = perceived["perceived_platform_m_s2"] - perceived["perceived_cue_m_s2"]
    perceived_raw = VestibularModel(sample_period_s=period).perceive_specific_force(raw_cue(plan, len(force_error)))
    raw_error = perceived["perceived_platform_m_s2"] - perceived_raw
    rate_error = perceived["perceived_platform_rate_rad_s"] - perceived["perceived_cue_rate_rad_s"]
    uncued = np.abs(perceived["platform_rate_rad_s"][:, :2] - timeline["angular"][:, :2])
    poses = timeline["poses"]
    stroke_use = _stroke_use(twin, poses)
    clearance = _clearance_m(twin, poses)
    thresholds = PerceptionThresholds().angular_velocity_rad_s[:2]
    return {
        "feasible": feasible,
        "reason": reason,
        "duration_s": round(len(poses) * period, 6),
        "planning_wall_s": round(planning_wall_s, 4),
        "perceived_specific_force_error_rms_m_s2": _rms_norm(force_error),
        "perceived_specific_force_error_rms_raw_m_s2": _rms_norm(raw_error),
        "perceived_angular_velocity_error_rms_rad_s": _rms_norm(rate_error),
        "peak_tilt_rate_rad_s": float(np.max(uncued)),
        "max_condition_number": float(np.nanmax(_condition_numbers(twin, poses))),
        "min_clearance_mm": float(np.nanmin(clearance) * 1e3),
        "max_stroke_use_fraction": float(np.max(stroke_use)),
        "_planning_cpu_s": planning_cpu_s,  # for the benchmark: the wall clock of a shared machine is inflated
        "_series": {
            "time_s": np.arange(len(poses)) * period,
            "perceived_cue_m_s2": perceived["perceived_cue_m_s2"],
            "perceived_cue_raw_m_s2": perceived_raw,
            "perceived_platform_m_s2": perceived["perceived_platform_m_s2"],
            "tilt_rad": poses[:, 3:5],
            "uncued_tilt_rate_rad_s": uncued,
            "tilt_rate_threshold_rad_s": np.asarray(thresholds),
            "stroke_use": stroke_use,
        },
    }


def _rms_norm(vectors: np.ndarray) -> float:
    """RMS over time of the norm over the axes of (N, 3) vectors."""
    import numpy as np

    return float(np.sqrt(np.mean(np.sum(vectors**2, axis=1))))


def _plot_scenario(name: str, results: dict[str, dict[str, Any]], directory: Path) -> list[str]:
    import numpy as np

    plt = pyplot()
    figure, axes = plt.subplots(3, 1, figsize=(10, 10), sharex=True)
    for index, (algorithm, result) in enumerate(results.items()):
        series = result["_series"]
        time_s = series["time_s"]
        axis = int(np.argmax(np.ptp(series["perceived_cue_m_s2"], axis=0)))
        if index == 0:
            axes[0].plot(time_s, series["perceived_cue_m_s2"][:, axis], "k--", label="cue (perceived)")
        axes[0].plot(time_s, series["perceived_platform_m_s2"][:, axis], label=f"{algorithm}: delivered at the head")
        axes[1].plot(time_s, series["tilt_rad"][:, 0], label=f"{algorithm}: roll (rad)")
        axes[1].plot(time_s, np.max(series["uncued_tilt_rate_rad_s"], axis=1), ":", label=f"{algorithm}: tilt rate")
        axes[2].plot(time_s, series["stroke_use"], label=algorithm)
    threshold = results[next(iter(results))]["_series"]["tilt_rate_threshold_rad_s"][0]
    axes[1].axhline(threshold, color="r", lw=0.8, label="roll-rate perception threshold (rad/s)")
    axes[0].set(title=f"{name}: perceived specific force at the head ({'xyz'[axis]} axis)", ylabel="m/s²")
    axes[1].set(title="tilt and uncued tilt rate against the perception threshold", ylabel="rad, rad/s")
    axes[2].set(title="stroke use (largest slider excursion / room to the stroke end)", ylabel="fraction")
    axes[2].set_xlabel("time (s)")
    for axis_plot in axes:
        axis_plot.grid(True, alpha=0.3)
        axis_plot.legend(fontsize=7)
    return [str(save_figure(figure, directory, f"cueing_{name}"))]


KEYS = (
    "feasible",
    "perceived_specific_force_error_rms_m_s2",
    "perceived_specific_force_error_rms_raw_m_s2",
    "perceived_angular_velocity_error_rms_rad_s",
    "peak_tilt_rate_rad_s",
    "max_condition_number",
    "max_stroke_use_fraction",
    "planning_wall_s",
)


def register(app: typer.Typer) -> None:
    cueing_app = typer.Typer(help="Motion cueing: classical washout against optimal cueing (issue 14).")
    app.add_typer(cueing_app, name="cueing")

    @cueing_app.command("plan")
    def plan_command(
        prescription_file: Path = typer.Argument(..., help="JSON body of POST /api/v1/prescriptions."),
        cueing: str = typer.Option("classical", "--cueing", help="classical | optimal"),
        as_json: bool = typer.Option(False, "--json"),
        robot_file: Path | None = ROBOT_OPTION,
    ) -> None:
        """Plan one prescription with one algorithm and judge it at the head."""
        from core.plan.prescription import CUEING_ALGORITHMS, PrescriptionError

        if cueing not in CUEING_ALGORITHMS:
            raise fail(f"cueing = {cueing!r}: must be one of {list(CUEING_ALGORITHMS)}", as_json=as_json)
        try:
            body = json.loads(prescription_file.read_text())
            result = evaluate(body, twin_from_option(robot_file), cueing)
        except (OSError, ValueError) as error:  # unreadable file, bad JSON, or a refused field
            raise fail(str(error), as_json=as_json) from error
        except (InvalidValueError, PrescriptionError) as error:
            raise fail(str(error), as_json=as_json) from error
        result.pop("_series"), result.pop("_planning_cpu_s")

        def human(data: dict[str, Any]) -> None:
            for key, value in data.items():
                console.print(f"{key:44} {value}")

        emit(result, as_json=as_json, human=human)

    @cueing_app.command("compare")
    def compare_command(
        scenario: list[str] = typer.Option(list(SUITE), "--scenario", help="Repeatable; default: the whole suite."),
        as_json: bool = typer.Option(False, "--json"),
        plot: Path | None = typer.Option(None, "--plot", help="Write one PNG per scenario to this folder."),
        robot_file: Path | None = ROBOT_OPTION,
    ) -> None:
        """Run the scenario suite through both algorithms on the twin; table (and PNGs)."""
        from core.plan.prescription import CUEING_ALGORITHMS

        unknown = [name for name in scenario if name not in SUITE]
        if unknown:
            raise fail(f"scenario = {unknown[0]!r}: must be one of {list(SUITE)}", as_json=as_json)
        try:
            twin = twin_from_option(robot_file)
        except InvalidValueError as error:
            raise fail(str(error), as_json=as_json) from error
        rows, plots = [], []
        with progress_bar("scenarios × algorithms", 2 * len(scenario)) as advance:
            for name in scenario:
                results = {}
                for algorithm in CUEING_ALGORITHMS:
                    results[algorithm] = evaluate(SUITE[name], twin, algorithm)
                    advance(1)
                if plot is not None:
                    plots += _plot_scenario(name, results, plot)
                for result in results.values():
                    result.pop("_series"), result.pop("_planning_cpu_s")
                rows.append({"name": name, **results})
        data: dict[str, Any] = {"scenarios": rows}
        if plot is not None:
            data["plots"] = plots

        def human(d: dict[str, Any]) -> None:
            from rich.table import Table

            table = Table(title="classical washout | optimal cueing, perceived at the head (1.6 m)")
            table.add_column("scenario")
            for key in KEYS:
                table.add_column(key.replace("_", " "), justify="right")
            for row in d["scenarios"]:
                for algorithm in CUEING_ALGORITHMS:
                    cells = [row[algorithm][key] for key in KEYS]
                    table.add_row(
                        f"{row['name']} ({algorithm})",
                        *[f"{c:.4g}" if isinstance(c, float) else str(c) for c in cells],
                    )
            console.print(table)
            for path in d.get("plots", []):
                console.print(f"plot: {path}")

        emit(data, as_json=as_json, human=human)
