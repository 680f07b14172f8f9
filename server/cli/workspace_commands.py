"""`ssp-rehab workspace`: the reachable workspace under every IK limit, in mm and degrees, with PNG plots."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from core.workspace import (
        AxisRange,
        Cloud,
        Reachability,
    )

import typer

from core.errors import InvalidValueError
from server.cli.output import console, emit, fail, progress_bar, pyplot, save_figure
from server.cli.robot_option import ROBOT_OPTION, twin_from_option

AXIS_KEYS = ("x_mm", "y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
AXIS_SCALE = (1e3, 1e3, 1e3, *([math.degrees(1.0)] * 3))  # SI → mm, deg at this edge


def _report(ranges: list[AxisRange], cloud: Cloud, frame: str) -> dict[str, Any]:
    cloud_min, cloud_max = cloud.extents()
    return {
        "frame": frame,
        "axes": {
            key: {
                "min": r.minimum * scale,
                "max": r.maximum * scale,
                "limited_by": {"min": r.limited_by_min, "max": r.limited_by_max},
                "cloud_min": low * scale,
                "cloud_max": high * scale,
            }
            for key, r, scale, low, high in zip(AXIS_KEYS, ranges, AXIS_SCALE, cloud_min, cloud_max, strict=True)
        },
        "cloud": {
            "samples": len(cloud.offsets),
            "reachable_fraction": cloud.reachable_fraction,
            "limiting_fraction_of_unreachable": cloud.limiting_fractions(),
        },
    }


def _print_report(data: dict[str, Any]) -> None:
    console.print(f"[bold]Workspace[/] ({data['frame']}), offsets from the neutral pose")
    console.print(f"{'axis':>10} {'min':>9} {'max':>9}   {'cloud min':>9} {'cloud max':>9}   limited by (min | max)")
    for key, axis in data["axes"].items():
        limited = f"{axis['limited_by']['min']} | {axis['limited_by']['max']}"
        console.print(
            f"{key:>10} {axis['min']:9.1f} {axis['max']:9.1f}   {axis['cloud_min']:9.1f} {axis['cloud_max']:9.1f}   "
            f"{limited}"
        )
    cloud = data["cloud"]
    console.print(f"6-DOF cloud: {cloud['reachable_fraction']:.1%} of {cloud['samples']} samples reachable")
    for reason, fraction in cloud["limiting_fraction_of_unreachable"].items():
        console.print(f"  {fraction:6.1%} of the unreachable break: {reason}")
    for path in data.get("plots", []):
        console.print(f"plot: {path}")


def _save_plots(reachability: Reachability, ranges: list[AxisRange], cloud: Cloud, directory: Path) -> list[str]:
    import numpy as np

    from core.workspace import AXIS_NAMES, reasons, slice_grid

    plt = pyplot()
    saved = []
    margin = 1.25
    for first, second in ((0, 1), (0, 2), (3, 4)):
        extents = (
            (ranges[first].minimum * margin, ranges[first].maximum * margin),
            (ranges[second].minimum * margin, ranges[second].maximum * margin),
        )
        values_a, values_b, flags = slice_grid(reachability, (first, second), extents, 201)
        figure, axes = plt.subplots(figsize=(6, 5))
        # Colour each point by its lowest violated limit bit (1-based); 0 is reachable.
        codes = np.array([(value & -value).bit_length() for value in range(256)])[flags]  # lowest limit bit
        image = axes.pcolormesh(
            values_a * AXIS_SCALE[first],
            values_b * AXIS_SCALE[second],
            codes,
            cmap=plt.get_cmap("Set2", 6),
            shading="auto",
            vmin=-0.5,
            vmax=5.5,
        )
        labels = ["reachable", *(reasons(1 << bit)[0] for bit in range(5))]
        colorbar = figure.colorbar(image, ticks=range(6))
        colorbar.ax.set_yticklabels(labels, fontsize=7)
        axes.set_xlabel(AXIS_KEYS[first])
        axes.set_ylabel(AXIS_KEYS[second])
        axes.set_title(f"{AXIS_NAMES[first]}-{AXIS_NAMES[second]} slice through neutral")
        saved.append(str(save_figure(figure, directory, f"workspace_{AXIS_NAMES[first]}{AXIS_NAMES[second]}_slice")))

    figure, (linear, angular) = plt.subplots(1, 2, figsize=(9, 4))
    for axes, indices, unit in ((linear, range(3), "mm"), (angular, range(3, 6), "deg")):
        names = [AXIS_NAMES[i] for i in indices]
        low = [ranges[i].minimum * AXIS_SCALE[i] for i in indices]
        high = [ranges[i].maximum * AXIS_SCALE[i] for i in indices]
        cloud_min, cloud_max = (e[list(indices)] * np.take(AXIS_SCALE, indices) for e in cloud.extents())
        axes.bar(names, np.subtract(high, low), bottom=low, color="tab:blue", alpha=0.7, label="single axis")
        axes.scatter(names, cloud_min, marker="v", color="k", label="6-DOF cloud extent")
        axes.scatter(names, cloud_max, marker="^", color="k")
        axes.axhline(0.0, color="grey", linewidth=0.5)
        axes.set_ylabel(f"offset from neutral ({unit})")
    linear.legend(fontsize=7)
    figure.suptitle("Reachable range per axis")
    saved.append(str(save_figure(figure, directory, "workspace_axis_ranges")))
    return saved


def register(app: typer.Typer) -> None:
    @app.command()
    def workspace(
        as_json: bool = typer.Option(False, "--json"),
        plot: Path | None = typer.Option(None, "--plot", help="Directory for PNG plots."),
        samples: int = typer.Option(200_000, "--samples", min=1, help="Random 6-DOF poses to sample."),
        stance: bool = typer.Option(
            False, "--stance", help="The twin's stance frame (both feet) instead of one robot."
        ),
        seed: int = typer.Option(0, "--seed"),
        robot_file: Path | None = ROBOT_OPTION,
    ) -> None:
        """Reachable range on each axis (mm, deg from neutral) under the stroke, cone, reach and singularity
        limits: bisection along each axis plus a random 6-DOF cloud."""
        from core.workspace import axis_ranges, robot_reachability, sample_cloud, stance_reachability

        try:
            twin = twin_from_option(robot_file)
            reachability = stance_reachability(twin) if stance else robot_reachability(twin.robot)
            ranges = axis_ranges(reachability)
        except (InvalidValueError, ValueError) as error:
            raise fail(str(error), as_json=as_json) from error
        with progress_bar("sampling 6-DOF poses", samples) as advance:
            cloud = sample_cloud(reachability, ranges, samples, seed=seed, progress=advance)
        data = _report(ranges, cloud, "twin stance frame" if stance else "one robot, base frame")
        if plot is not None:
            data["plots"] = _save_plots(reachability, ranges, cloud, plot)
        emit(data, as_json=as_json, human=_print_report)
