"""`ssp-rehab layout search`: the twin layout study (issue 13 §3), with pymoo; mm and degrees at this edge."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from core.layout import LayoutCandidate, LayoutResult
    from core.robot import TwinRobot

import typer

from server.cli.output import console, emit, fail, progress_bar, pyplot, save_figure

AXIS_LABELS = {"x": "surge (mm)", "y": "sway (mm)", "roll": "roll (deg)", "pitch": "pitch (deg)"}


def _layout_line(layout: dict[str, Any]) -> str:
    return (
        f"bases ±{layout['base_offset_y_m'] * 1e3:.0f} mm across, stagger ±{layout['stagger_x_m'] * 1e3:.0f} mm, "
        f"yaw ±{abs(layout['base_yaw_deg']):.1f}°, feet {layout['feet_apart_m'] * 1e3:.0f} mm apart, "
        f"{'mirrored' if layout['mirrored'] else 'identical'}"
    )


def _print(data: dict[str, Any]) -> None:
    from core.layout import CLINICAL_AXES

    console.print(
        f"[bold]Layout search[/]: {data['evaluations']} layouts in {data['wall_s']:.1f} s "
        f"(population {data['population']}, {data['generations']} generations, seed {data['seed']})"
    )
    header = "  ".join(f"{AXIS_LABELS[a]:>12}" for a in CLINICAL_AXES)
    console.print(f"{'#':>3}  {header}  {'volume':>6}  {'force (N)':>9}  {'arm (mm)':>8}  layout")
    rows = [("ref", data["reference"])] if data["reference"] else []
    rows += [(str(i), entry) for i, entry in enumerate(data["pareto"])]
    for label, entry in rows:
        metrics = entry["metrics"]
        reach = "  ".join(f"{metrics['symmetric_reach'][a]:12.1f}" for a in CLINICAL_AXES)
        mark = "*" if label == str(data["recommended"]) else " "
        console.print(
            f"{label:>3}{mark} {reach}  {metrics['volume_fraction']:6.3f}  {metrics['peak_force_n']:9.0f}  "
            f"{metrics['cantilever_mm']:8.0f}  {_layout_line(entry['layout'])}"
        )
    console.print("reach: the smaller of the two directions from neutral; * recommended")
    for key in ("plots", "toml"):
        for path in data.get(key, []):
            console.print(f"{key}: {path}")


def _compared_layouts(result: LayoutResult) -> list[tuple[str, TwinRobot, bool]]:
    """(label, twin, clearance checked) for the plots: the layout before issue 13 (its rods cross, so
    its workspace is shown without the clearance check), today's default and the recommendation."""
    from core.robot import named_twin

    compared = [("before issue 13 (rods cross; clearance ignored)", named_twin("legacy-interleaved"), False)]
    if result.reference_layout is not None:
        compared.append(("today's default", result.reference_layout.twin(), True))
    compared.append(("recommended", result.pareto[result.recommended][0].twin(), True))
    return compared


def _plots(result: LayoutResult, directory: Path) -> list[str]:
    import numpy as np

    from core.layout import CLINICAL_AXES
    from core.workspace import axis_ranges, slice_grid, stance_reachability

    plt = pyplot()
    compared = _compared_layouts(result)
    ranges = {
        label: {r.axis: r for r in axis_ranges(stance_reachability(twin, clearance_check=checked), scan_points=400)}
        for label, twin, checked in compared
    }
    paths = []
    figure, axes = plt.subplots(1, len(CLINICAL_AXES), figsize=(14, 3.8))
    for axis_plot, axis in zip(axes, CLINICAL_AXES, strict=True):
        scale = 1e3 if axis in ("x", "y") else math.degrees(1.0)
        for position, (label, _, _) in enumerate(compared):
            reach = ranges[label][axis]
            axis_plot.bar(position, (reach.maximum - reach.minimum) * scale, bottom=reach.minimum * scale, width=0.6)
        axis_plot.axhline(0.0, color="black", linewidth=0.6)
        axis_plot.set_xticks(range(len(compared)), [label.split(" (")[0] for label, _, _ in compared], fontsize=7)
        axis_plot.set_title(AXIS_LABELS[axis])
    figure.suptitle("Stance workspace at the singularity margin: per-axis reach from neutral")
    paths.append(str(save_figure(figure, directory, "layout_axis_ranges")))

    figure, axes = plt.subplots(1, len(compared), figsize=(5.2 * len(compared), 4.6), squeeze=False)
    extent = math.radians(20.0)
    for axis_plot, (label, twin, checked) in zip(axes[0], compared, strict=True):
        reachability = stance_reachability(twin, clearance_check=checked)
        roll, pitch, flags = slice_grid(reachability, (3, 4), ((-extent, extent),) * 2, 81)
        axis_plot.contourf(np.degrees(roll), np.degrees(pitch), flags == 0, levels=[-0.5, 0.5, 1.5], cmap="Greens")
        axis_plot.set_xlabel("stance roll (deg)")
        axis_plot.set_ylabel("stance pitch (deg)")
        axis_plot.set_title(label, fontsize=9)
    figure.suptitle("Reachable stance roll–pitch (dark green)")
    paths.append(str(save_figure(figure, directory, "layout_roll_pitch")))
    return paths


def register(app: typer.Typer) -> None:
    layout_app = typer.Typer(help="Where the two robots stand: the layout study (docs/kinematics.md).")
    app.add_typer(layout_app, name="layout")

    @layout_app.command("search")
    def search(
        population: int = typer.Option(24, "--population", help="NSGA-II population"),
        generations: int = typer.Option(8, "--generations", help="NSGA-II generations"),
        seed: int = typer.Option(1, "--seed"),
        stagger_max_mm: float = typer.Option(
            0.0, "--stagger-max", help="largest stagger along the rails (mm); 0 keeps the sagittal symmetry"
        ),
        as_json: bool = typer.Option(False, "--json"),
        plot_dir: Path | None = typer.Option(None, "--plot", help="write PNG plots into this directory"),
        toml_path: Path | None = typer.Option(None, "--toml", help="write the recommended layout's robot TOML"),
        progress: bool = typer.Option(True, "--progress/--no-progress"),
    ) -> None:
        """Search the twin placement for the stance workspace and the drive force (pymoo NSGA-II)."""
        from core.layout import LayoutSearchError, layout_search
        from core.robot import save_twin

        try:
            with progress_bar("layout search (generations)", generations, enabled=progress) as advance:
                result = layout_search(
                    population=population,
                    generations=generations,
                    seed=seed,
                    stagger_max_m=stagger_max_mm / 1e3,
                    progress=advance,
                )
        except (LayoutSearchError, RuntimeError) as error:
            raise fail(str(error), as_json=as_json) from error
        data = result.to_dict()
        recommended: LayoutCandidate = result.pareto[result.recommended][0]
        if toml_path is not None:
            toml_path.parent.mkdir(parents=True, exist_ok=True)
            save_twin(recommended.twin(), toml_path)
            data["toml"] = [str(toml_path)]
        if plot_dir is not None:
            data["plots"] = _plots(result, plot_dir)
        emit(data, as_json=as_json, human=_print)
