"""`ssp-rehab posturography measures FILE`: Prieto's centre-of-pressure measures of any recording (issue 22 §5;
definitions in docs/posturography.md).

- A CSV with the columns `t_s,cop_ml_mm,cop_ap_mm`, uniformly sampled (another force plate, an earlier study);
- a C3D exported by the product (its two foot plates' Fz, Px and Py, the plates placed by FORCE_PLATFORM:CORNERS):
  the net COP of both feet over the longest stretch in which the plates carry someone, as for a run's own
  balance measures (server/sessions/balance.py).

By default the COP is low-pass filtered as the product filters its own runs (`core.posturography.lowpass_cop`:
onto a uniform grid at the median interval, 5 Hz, 4th-order Butterworth, zero phase). `--no-filter` computes
on the signal exactly as given: no resampling, no filtering, no re-centring beyond the measures' own reference
to the mean COP.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

from server.cli.output import console, emit, fail

if TYPE_CHECKING:
    import numpy as np

CSV_COLUMNS = ("t_s", "cop_ml_mm", "cop_ap_mm")
UNIFORM_TOLERANCE = 0.01  # a CSV's sample intervals may differ from their median by this fraction
# (printed key, label, SwayMetrics field, factor to the printed unit, unit)
MEASURES = (
    ("mean_distance_mm", "mean distance", "mean_distance_m", 1e3, "mm"),
    ("rms_distance_mm", "RMS distance", "rms_distance_m", 1e3, "mm"),
    ("range_ml_mm", "range, medio-lateral", "range_ml_m", 1e3, "mm"),
    ("range_ap_mm", "range, anterior-posterior", "range_ap_m", 1e3, "mm"),
    ("total_excursion_mm", "total excursion", "path_length_m", 1e3, "mm"),
    ("mean_velocity_mm_s", "mean velocity", "mean_velocity_m_s", 1e3, "mm/s"),
    ("mean_velocity_ml_mm_s", "mean velocity, medio-lateral", "mean_velocity_ml_m_s", 1e3, "mm/s"),
    ("mean_velocity_ap_mm_s", "mean velocity, anterior-posterior", "mean_velocity_ap_m_s", 1e3, "mm/s"),
    ("confidence_circle_area_95_mm2", "95 % confidence circle area", "confidence_circle_area_95_m2", 1e6, "mm²"),
    ("confidence_ellipse_area_95_mm2", "95 % confidence ellipse area", "confidence_ellipse_area_95_m2", 1e6, "mm²"),
    ("sway_area_per_second_mm2_s", "sway area per second", "sway_area_per_second_m2_s", 1e6, "mm²/s"),
    ("mean_frequency_hz", "mean frequency", "mean_frequency_hz", 1.0, "Hz"),
)


class RecordingError(ValueError):
    """A recording that cannot be measured: names the field, the value and the limit."""


def read_cop_csv(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(time s, COP m as (AP, ML)) of a `t_s,cop_ml_mm,cop_ap_mm` CSV; refuses gaps, non-numbers and uneven
    sampling, naming the row."""
    import numpy as np

    with path.open(encoding="utf-8") as handle:
        header = [name.strip() for name in handle.readline().split(",")]
        if tuple(header) != CSV_COLUMNS:
            raise RecordingError(f"columns = {','.join(header)!r}: expected {','.join(CSV_COLUMNS)!r}")
        rows = []
        for number, line in enumerate(handle, start=2):
            if not line.strip():
                continue
            fields = line.split(",")
            try:
                values = [float(field) for field in fields]
            except ValueError:
                raise RecordingError(f"row {number} = {line.strip()!r}: every field must be a number") from None
            if len(values) != len(CSV_COLUMNS) or not all(math.isfinite(v) for v in values):
                raise RecordingError(f"row {number} = {line.strip()!r}: three finite numbers expected")
            rows.append(values)
    data = np.array(rows, dtype=float).reshape(-1, len(CSV_COLUMNS))
    if len(data) < 3:
        raise RecordingError(f"rows = {len(data)}: at least 3 samples are needed")
    intervals = np.diff(data[:, 0])
    median = float(np.median(intervals))
    if median <= 0:
        raise RecordingError(f"t_s: median interval = {median:g} s: times must increase")
    worst = int(np.argmax(np.abs(intervals - median)))
    if abs(intervals[worst] - median) > UNIFORM_TOLERANCE * median:
        raise RecordingError(
            f"t_s at row {worst + 3} = {data[worst + 1, 0]:g} s: an interval of {intervals[worst]:g} s against the "
            f"median {median:g} s (limit ±{UNIFORM_TOLERANCE:.0%}): the samples must be uniform"
        )
    return data[:, 0], np.column_stack([data[:, 2], data[:, 1]]) * 1e-3


def read_cop_c3d(path: Path) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """(time s, net COP m as (AP, ML) in the lab frame, the window) of a C3D the product exported: both plates'
    COP placed by their corners, weighted by their vertical force, over the longest loaded stretch."""
    import ezc3d
    import numpy as np

    from core.posturography import net_cop
    from server.exports.c3d import COP_FORCE_THRESHOLD_N, PLATE_CHANNELS
    from server.sessions.balance import LOADED_PLATES_N, MIN_LOADED_SAMPLES, longest_loaded_stretch

    try:
        c3d = ezc3d.c3d(str(path))
    except (RuntimeError, OSError) as error:
        raise RecordingError(f"file = {path}: not a readable C3D ({error})") from error
    parameters = c3d["parameters"]
    labels = list(parameters["ANALOG"]["LABELS"]["value"])
    rate_hz = float(parameters["ANALOG"]["RATE"]["value"][0])
    analogs = c3d["data"]["analogs"][0]  # (channels, samples)
    try:
        corners = np.asarray(parameters["FORCE_PLATFORM"]["CORNERS"]["value"], dtype=float).reshape(3, 4, -1)
    except KeyError:
        raise RecordingError(f"file = {path}: no FORCE_PLATFORM:CORNERS; not a C3D exported by ssp-rehab") from None
    plates = corners.shape[2]
    forces, cops = [], []
    for number in range(1, plates + 1):
        try:
            fz, px, py = (analogs[labels.index(f"{name}{number}")] for name in ("Fz", "Px", "Py"))
        except ValueError:
            raise RecordingError(f"ANALOG:LABELS = {labels[:12]}…: no {PLATE_CHANNELS} of plate {number}") from None
        plate = corners[:, :, number - 1]  # corners: +x+y, -x+y, -x-y, +x-y of the plate
        centre = plate[:2].mean(axis=1)
        x_axis = (plate[:2, 0] - plate[:2, 1]) / np.linalg.norm(plate[:2, 0] - plate[:2, 1])
        y_axis = (plate[:2, 1] - plate[:2, 2]) / np.linalg.norm(plate[:2, 1] - plate[:2, 2])
        loaded = np.nan_to_num(fz) >= COP_FORCE_THRESHOLD_N  # COP is NaN (meaningless) below it
        forces.append(np.where(loaded, fz, 0.0))
        local = np.where(loaded[:, None], np.column_stack([px, py]), 0.0)
        cops.append(centre + local[:, :1] * x_axis + local[:, 1:] * y_axis)
    force = np.column_stack(forces)
    stretch = longest_loaded_stretch(force)
    if stretch.stop - stretch.start < MIN_LOADED_SAMPLES:
        raise RecordingError(
            f"plate Fz: loaded (≥ {LOADED_PLATES_N:g} N together) for {stretch.stop - stretch.start} samples in a "
            f"row; at least {MIN_LOADED_SAMPLES} are needed"
        )
    cop = net_cop(force[stretch], np.stack(cops, axis=1)[stretch], np.zeros((plates, 2)))
    time_s = np.arange(stretch.start, stretch.stop) / rate_hz
    window = {"from_s": float(time_s[0]), "to_s": float(time_s[-1]), "samples": len(time_s), "rate_hz": rate_hz}
    return time_s, cop, window


def measures(path: Path, *, filtered: bool = True) -> dict[str, Any]:
    """Prieto's measures of the recording at `path` (CSV or C3D), in the units their keys name."""
    from core.posturography import COP_LOWPASS_CUTOFF_HZ, COP_LOWPASS_ORDER, filtered_sway_metrics, sway_metrics

    if not path.is_file():
        raise RecordingError(f"file = {path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".csv":
        time_s, cop = read_cop_csv(path)
        window = {"from_s": float(time_s[0]), "to_s": float(time_s[-1]), "samples": len(time_s)}
    elif suffix == ".c3d":
        time_s, cop, window = read_cop_c3d(path)
    else:
        raise RecordingError(f"file = {path}: the extension {suffix or '(none)'!r} is neither .csv nor .c3d")
    metrics = (filtered_sway_metrics if filtered else sway_metrics)(time_s, cop)
    values = metrics.to_dict()
    return {
        "file": str(path),
        "window": {**window, "duration_s": metrics.duration_s},
        "filter": (
            f"low-pass {COP_LOWPASS_CUTOFF_HZ:g} Hz, Butterworth order {COP_LOWPASS_ORDER}, zero phase, on a uniform "
            "grid at the median interval"
            if filtered
            else "none: the signal as given"
        ),
        "measures": {key: values[field] * factor for key, _, field, factor, _ in MEASURES},
        "units": {key: unit for key, _, _, _, unit in MEASURES},
    }


def _print(data: dict[str, Any]) -> None:
    window = data["window"]
    console.print(f"{data['file']}: {window['samples']} samples, {window['duration_s']:.2f} s analysed")
    console.print(f"filter: {data['filter']}")
    for key, label, _, _, _ in MEASURES:
        console.print(f"  {label:<34} {data['measures'][key]:12.4f} {data['units'][key]}")


def register(app: typer.Typer) -> None:
    posturography_app = typer.Typer(
        help="Balance measures of centre-of-pressure recordings (docs/posturography.md).", no_args_is_help=True
    )

    @posturography_app.command("measures")
    def measures_command(
        file: Path = typer.Argument(..., help="A CSV (t_s,cop_ml_mm,cop_ap_mm) or a C3D the product exported."),
        no_filter: bool = typer.Option(False, "--no-filter", help="On the signal exactly as given (no filter)."),
        as_json: bool = typer.Option(False, "--json", help="Print the measures as JSON."),
    ) -> None:
        """Prieto et al. (1996) centre-of-pressure measures: distances, ranges, excursion, velocities, areas,
        mean frequency."""
        from core.patient import ParameterError

        try:
            data = measures(file, filtered=not no_filter)
        except (RecordingError, ParameterError) as error:
            raise fail(str(error), as_json=as_json) from error
        emit(data, as_json=as_json, human=_print)

    app.add_typer(posturography_app, name="posturography")
