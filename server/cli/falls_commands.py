"""`ssp-rehab simulate-cohort` and `ssp-rehab evaluate-falls`: labelled simulated sessions and the fall
detectors scored against them (issue 8; docs/falls.md).

A session log is `<name>.npz` (telemetry columns, SI) with a `<name>.json` sidecar (format, sample period,
patient anthropometrics, perturbation schedule and the ground-truth fall onsets).
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    import numpy as np

    from core.falls import (
        FallDetectorConfig,
        FallEvent,
        LabelledLog,
        MatchingWindow,
        SessionDetections,
    )

import typer

from server.cli.output import console, emit, fail, progress_bar, pyplot, save_figure

LOG_FORMAT = "ssp-rehab-session-log/1"
POST_FALL_S = 3.0  # the supervisor pauses on a fall; the simulated session ends this long after the onset
COLUMN_UNITS = {
    "time_s": "s",
    "plate_force_z_n": "N, (right, left)",
    "plate_cop_m": "m, [foot (right, left), (x anterior, y left)] in each foot-plate frame",
    "harness_load_n": "N",
    "support_acceleration_m_s2": "m/s², world frame, gravity excluded",
    "support_tilt_rad": "rad, (roll, pitch)",
    "support_angular_velocity_rad_s": "rad/s",
    "sway_angle_rad": "rad, (AP forward +, ML left +), simulator ground truth",
    "fallen": "bool, simulator ground truth",
}


# --- session logs ------------------------------------------------------------------------------------


def write_session_log(directory: Path, name: str, columns: dict[str, np.ndarray], metadata: dict[str, Any]) -> Path:
    import numpy as np

    path = directory / f"{name}.npz"
    np.savez_compressed(path, **columns)  # type: ignore[arg-type]  # numpy stubs type **kwds as the flag
    sidecar = {"format": LOG_FORMAT, "session": name, "columns": {k: COLUMN_UNITS.get(k, "") for k in columns}}
    (directory / f"{name}.json").write_text(json.dumps({**sidecar, **metadata}, indent=2))
    return path


def _stack_parquet_column(values: Any) -> np.ndarray:
    import numpy as np

    return np.asarray(values.to_pylist(), dtype=float)


def read_session_log(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Columns and sidecar metadata of one `.npz` or `.parquet` log (list columns become (N, k) arrays)."""
    import numpy as np

    from core.patient import ParameterError

    if path.suffix == ".npz":
        with np.load(path) as archive:
            columns = {name: archive[name] for name in archive.files}
    elif path.suffix == ".parquet":
        import pyarrow.parquet as pq

        table = pq.read_table(path)
        columns = {name: _stack_parquet_column(table.column(name)) for name in table.column_names}
    else:
        raise ParameterError("log", str(path), "must be a .npz or .parquet session log")
    if "plate_cop_m" in columns:
        columns["plate_cop_m"] = columns["plate_cop_m"].reshape(-1, 2, 2)
    missing = [c for c in ("time_s", "plate_force_z_n", "plate_cop_m", "harness_load_n") if c not in columns]
    if missing:
        raise ParameterError(f"{path.name}:{missing[0]}", None, "required telemetry column is missing")
    sidecar = path.with_suffix(".json")
    metadata = json.loads(sidecar.read_text()) if sidecar.exists() else {}
    return columns, metadata


def support_acceleration_z(columns: dict[str, np.ndarray]) -> np.ndarray | None:
    """The support's vertical acceleration (m/s², gravity excluded), when the log has it."""
    import numpy as np

    acceleration = columns.get("support_acceleration_m_s2")
    return None if acceleration is None else np.ascontiguousarray(acceleration[:, 2], dtype=float)


def _log_paths(logs: list[Path]) -> list[Path]:
    from core.patient import ParameterError

    paths: list[Path] = []
    for entry in logs:
        if entry.is_dir():
            paths.extend(sorted(p for p in entry.iterdir() if p.suffix in (".npz", ".parquet")))
        elif entry.exists():
            paths.append(entry)
        else:
            raise ParameterError("LOGS", str(entry), "no such file or directory")
    if not paths:
        raise ParameterError("LOGS", [str(p) for p in logs], "holds no .npz or .parquet session logs")
    return paths


# --- simulate-cohort ---------------------------------------------------------------------------------


def simulate_session(
    rng: np.random.Generator, seed: int, duration_s: float, sample_period_s: float, impaired_share: float
) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """One random patient under a random perturbation schedule; ends `POST_FALL_S` after a fall."""
    import numpy as np

    from core.patient import FootGeometry, random_patient, random_perturbations, simulate_trial

    params = random_patient(rng, impaired_share)
    perturbations = random_perturbations(rng, duration_s)
    motion, trajectory = simulate_trial(params, perturbations, duration_s, sample_period_s, seed)
    fell = not math.isnan(trajectory.fall_onset_s)
    count = len(motion.time_s)
    if fell:
        count = min(count, int(np.searchsorted(motion.time_s, trajectory.fall_onset_s + POST_FALL_S)) + 1)
    signal = np.float32
    columns = {
        "time_s": motion.time_s[:count],
        "plate_force_z_n": trajectory.plate_force_z_n[:count].astype(signal),
        "plate_cop_m": trajectory.plate_cop_m[:count].astype(signal),
        "harness_load_n": trajectory.harness_load_n[:count].astype(signal),
        "support_acceleration_m_s2": motion.acceleration_m_s2[:count].astype(signal),
        "support_tilt_rad": motion.tilt_rad[:count].astype(signal),
        "support_angular_velocity_rad_s": motion.angular_velocity_rad_s[:count].astype(signal),
        "sway_angle_rad": trajectory.sway_angle_rad[:count].astype(signal),
        "fallen": trajectory.fallen[:count],
    }
    foot = FootGeometry.from_height(params.height_m)
    metadata = {
        "sample_period_s": sample_period_s,
        "duration_s": float(motion.time_s[count - 1]),
        "seed": seed,
        "patient": {
            "preset": params.preset_name,
            "body_mass_kg": params.body_mass_kg,
            "height_m": params.height_m,
            "parameters": params.to_dict(),
        },
        "anthropometrics": {
            "body_weight_n": params.body_weight_n,
            "com_height_above_ankle_m": params.com_height_above_ankle_m,
            "moment_of_inertia_kg_m2": params.moment_of_inertia_kg_m2,
            "foot_heel_m": foot.heel_m,
            "foot_toe_m": foot.toe_m,
            "foot_half_breadth_m": foot.half_breadth_m,
        },
        "perturbations": [p.to_dict() for p in perturbations],
        "falls": [{"onset_s": trajectory.fall_onset_s, "response": trajectory.fall_response}] if fell else [],
        "fall_definition": (
            "balance lost: the extrapolated COM left the base of support (then a step, a grab or a harness "
            "catch), or the harness took up its slack"
        ),
    }
    return columns, metadata


def _print_cohort(data: dict[str, Any]) -> None:
    console.print(
        f"{data['sessions']} sessions ({data['healthy']} healthy, {data['impaired']} impaired), "
        f"{data['falls']} labelled falls, {data['hours']:.2f} h, written to {data['out']}"
    )


# --- evaluate-falls ----------------------------------------------------------------------------------


def _load_truth(path: Path) -> dict[str, list[float]]:
    """{"session name": [onset_s, ...]} (a session absent from the file has no falls)."""
    from core.patient import ParameterError

    data = json.loads(path.read_text())
    if not isinstance(data, dict) or not all(isinstance(v, list) for v in data.values()):
        raise ParameterError("--truth", str(path), 'must be a JSON object {"session": [onset_s, ...]}')
    return {str(k): [float(v) for v in values] for k, values in data.items()}


def _detector_config(
    metadata: dict[str, Any], overrides: dict[str, Any], body_mass_kg: float | None
) -> FallDetectorConfig:
    from core.falls import FallDetectorConfig
    from core.patient import ParameterError

    patient = metadata.get("patient", {})
    mass = patient.get("body_mass_kg", body_mass_kg)
    if mass is None:
        raise ParameterError("--body-mass-kg", None, "needed for logs without a sidecar giving the patient's mass")
    height_m = patient.get("height_m")
    base = FallDetectorConfig.for_patient(mass, height_m) if height_m else FallDetectorConfig(body_mass_kg=mass)
    data = base.to_dict()
    for section in ("harness", "cop", "unload", "fused"):  # evaluation scores every detector
        data[section]["enabled"] = True
    for section, values in overrides.items():
        data[section] = {**data.get(section, {}), **values}
    return FallDetectorConfig.from_dict(data)


def labelled_logs(
    paths: list[Path],
    truth: dict[str, list[float]] | None,
    overrides: dict[str, Any],
    body_mass_kg: float | None,
    advance: Any,
) -> tuple[list[LabelledLog], dict[str, tuple[dict[str, np.ndarray], dict[str, Any]]]]:
    """Each log's detector inputs, configuration and labelled onsets (and the raw columns, for plots)."""
    labelled, logs = [], {}
    for path in paths:
        columns, metadata = read_session_log(path)
        name = metadata.get("session", path.stem)
        onsets = truth.get(name, []) if truth is not None else None
        labelled.append(labelled_log(name, columns, metadata, overrides, body_mass_kg, onsets))
        logs[name] = (columns, metadata)
        advance(1)
    return labelled, logs


def labelled_log(
    name: str,
    columns: dict[str, np.ndarray],
    metadata: dict[str, Any],
    overrides: dict[str, Any] | None = None,
    body_mass_kg: float | None = None,
    onsets: list[float] | None = None,
) -> LabelledLog:
    """One log as the evaluation takes it; the onsets default to the sidecar's labelled falls."""
    import numpy as np

    from core.falls import LabelledLog

    time_s = columns["time_s"].astype(float)
    if onsets is None:
        onsets = [fall["onset_s"] for fall in metadata.get("falls", [])]
    return LabelledLog(
        name=name,
        config=_detector_config(metadata, overrides or {}, body_mass_kg),
        sample_period_s=float(metadata.get("sample_period_s", np.median(np.diff(time_s)))),
        time_s=time_s,
        plate_force_z_n=columns["plate_force_z_n"].astype(float),
        plate_cop_m=columns["plate_cop_m"].astype(float),
        harness_load_n=columns["harness_load_n"].astype(float),
        support_acceleration_z_m_s2=support_acceleration_z(columns),
        fall_onsets_s=tuple(float(onset) for onset in onsets),
    )


def detections(logs: list[LabelledLog]) -> list[SessionDetections]:
    """Every enabled detector's events on each log, at each log's configuration."""
    from core.falls import SessionDetections, detect_falls

    return [
        SessionDetections(
            log.name,
            log.duration_s,
            log.fall_onsets_s,
            tuple(
                detect_falls(
                    log.config,
                    log.sample_period_s,
                    log.time_s,
                    log.plate_force_z_n,
                    log.plate_cop_m,
                    log.harness_load_n,
                    log.support_acceleration_z_m_s2,
                )
            ),
        )
        for log in logs
    ]


def operating_threshold(config: FallDetectorConfig, detector: str) -> float:
    from core.falls import ROC_PARAMETERS

    section, parameter = ROC_PARAMETERS[detector]
    return float(getattr(getattr(config, section), parameter))


def roc_report(logs: list[LabelledLog], window: MatchingWindow, scores: list[Any]) -> dict[str, Any]:
    """Per detector: the ROC points and the operating point (the configured threshold's score)."""
    from core.falls import ROC_PARAMETERS, roc_curve

    by_name = {score.detector: score for score in scores}
    report = {}
    for detector in ROC_PARAMETERS:
        operating = by_name[detector]
        report[detector] = {
            "parameter": ".".join(ROC_PARAMETERS[detector]),
            "points": [point.to_dict() for point in roc_curve(logs, detector, window=window)],
            "operating_point": {
                "threshold": operating_threshold(logs[0].config, detector),
                "sensitivity": operating.sensitivity,
                "false_alarms_per_hour": operating.false_alarms_per_hour,
            },
        }
    return report


def tuning_combinations() -> int:
    import numpy as np

    from core.falls import TUNING_GRID

    return int(np.prod([len(values) for values in TUNING_GRID.values()]))


def _print_scores(data: dict[str, Any]) -> None:
    console.print(
        f"{data['sessions']} sessions, {data['hours']:.2f} h, {data['falls']} labelled falls; "
        f"window {-data['window']['before_s']:+.1f} s .. {data['window']['after_s']:+.1f} s around each onset"
    )
    console.print(f"{'detector':<18}{'sensitivity':>12}{'false/h':>10}{'latency median':>16}{'p95':>9}")
    for score in data["detectors"]:

        def ms(value: float) -> str:
            return "—" if value is None or not math.isfinite(value) else f"{value * 1e3:.0f} ms"

        sensitivity = score["sensitivity"]
        shown = "—" if not math.isfinite(sensitivity) else f"{100 * sensitivity:.0f} %"
        console.print(
            f"{score['detector']:<18}{shown:>12}{score['false_alarms_per_hour']:>10.2f}"
            f"{ms(score['latency_median_s']):>16}{ms(score['latency_p95_s']):>9}"
        )
    for detector, curve in data.get("roc", {}).items():
        operating = curve["operating_point"]
        console.print(
            f"operating point {detector}: {curve['parameter']} = {operating['threshold']:g} "
            f"(ROC over {len(curve['points'])} thresholds in --json and roc.png)"
        )
    for path in data.get("plots", []):
        console.print(f"plot: {path}")


def _plot(
    directory: Path,
    scores: list[Any],
    sessions: list[SessionDetections],
    logs: dict[str, tuple[dict[str, np.ndarray], dict[str, Any]]],
    window: MatchingWindow,
) -> list[str]:
    import numpy as np

    plt = pyplot()
    paths = []
    figure, axes = plt.subplots(figsize=(7, 4))
    for score in scores:
        if score.latencies_s:
            axes.hist(np.asarray(score.latencies_s) * 1e3, bins=20, alpha=0.5, label=score.detector)
    axes.set_xlabel("detection latency after the labelled onset (ms)")
    axes.set_ylabel("falls")
    axes.set_title("Fall detection latency")
    axes.legend()
    paths.append(str(save_figure(figure, directory, "latency_histogram")))

    figure, axes = plt.subplots(figsize=(7, 4))
    names = [score.detector for score in scores]
    sensitivities = [0.0 if math.isnan(s.sensitivity) else 100 * s.sensitivity for s in scores]
    bars = axes.bar(names, sensitivities, color="tab:blue")
    for bar, score in zip(bars, scores, strict=True):
        axes.annotate(
            f"{score.false_alarms_per_hour:.1f} FA/h",
            (bar.get_x() + bar.get_width() / 2, bar.get_height()),
            ha="center",
            va="bottom",
        )
    axes.set_ylim(0, 110)
    axes.set_ylabel("sensitivity (%)")
    axes.set_title("Sensitivity per detector (false alarms per hour above each bar)")
    paths.append(str(save_figure(figure, directory, "sensitivity")))

    def detected_in_window(session: SessionDetections) -> bool:
        onset = session.fall_onsets_s[0] if session.fall_onsets_s else math.nan
        return any(onset - window.before_s <= e.detected_s <= onset + window.after_s for e in session.events)

    example = next((s for s in sessions if detected_in_window(s)), None)
    if example is not None:
        columns, _ = logs[example.name]
        time_s = columns["time_s"]
        onset = example.fall_onsets_s[0]
        shown = (time_s > onset - 4.0) & (time_s < onset + POST_FALL_S)
        figure, axes_list = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
        axes_list[0].plot(time_s[shown], columns["harness_load_n"][shown], label="harness load")
        axes_list[0].set_ylabel("N")
        axes_list[1].plot(time_s[shown], columns["plate_force_z_n"][shown, 0], label="Fz right")
        axes_list[1].plot(time_s[shown], columns["plate_force_z_n"][shown, 1], label="Fz left")
        axes_list[1].set_ylabel("N")
        axes_list[2].plot(time_s[shown], columns["plate_cop_m"][shown, 0, 0] * 1e3, label="COP x right")
        axes_list[2].plot(time_s[shown], columns["plate_cop_m"][shown, 1, 0] * 1e3, label="COP x left")
        axes_list[2].set_ylabel("mm")
        axes_list[2].set_xlabel("time (s)")
        shown_events = [e for e in example.events if onset - window.before_s <= e.detected_s <= onset + POST_FALL_S]
        for axes in axes_list:
            axes.axvline(onset, color="black", linestyle="--", label="labelled onset")
            for event in shown_events:
                axes.axvline(event.detected_s, color="tab:red", alpha=0.6)
            axes.legend(loc="upper left", fontsize=7)
        for row, event in enumerate(shown_events):
            position = (event.detected_s, 0.9 - 0.12 * row)
            axes_list[0].annotate(f" {event.detector}", position, xycoords=("data", "axes fraction"), fontsize=7)
        axes_list[0].set_title(f"{example.name}: labelled onset (dashed) and detections (red)")
        paths.append(str(save_figure(figure, directory, "example_trace")))
    return paths


def register(app: typer.Typer) -> None:
    @app.command("simulate-cohort")
    def simulate_cohort(
        out: Path = typer.Argument(..., help="Directory for the session logs (created if missing)."),
        patients: int = typer.Option(20, "--patients", help="Number of simulated patients (one session each)."),
        seed: int = typer.Option(0, "--seed", help="Seed of the whole cohort."),
        duration_s: float = typer.Option(60.0, "--duration-s", help="Session length (s) unless a fall ends it."),
        rate_hz: float = typer.Option(1000.0, "--rate-hz", help="Simulation and logging rate (Hz)."),
        impaired_share: float = typer.Option(0.5, "--impaired-share", help="Share of impaired patients, 0–1."),
        as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON."),
    ) -> None:
        """Simulated sessions with labelled falls: random patients under random translation/tilt pulses."""
        import numpy as np

        from core.patient import ParameterError

        try:
            if not 1 <= patients <= 100_000:
                raise ParameterError("--patients", patients, "must be in [1, 100000]")
            if not 5.0 <= duration_s <= 24 * 3600.0:
                raise ParameterError("--duration-s", duration_s, "must be in [5, 86400] s")
            if not 50.0 <= rate_hz <= 10_000.0:
                raise ParameterError("--rate-hz", rate_hz, "must be in [50, 10000] Hz")
            out.mkdir(parents=True, exist_ok=True)
            children = np.random.SeedSequence(seed).spawn(patients)
            counts = {"healthy": 0, "impaired": 0, "falls": 0}
            hours = 0.0
            files = []
            with progress_bar("simulating sessions", patients, enabled=True) as advance:
                for index, child in enumerate(children, start=1):
                    rng = np.random.default_rng(child)
                    session_seed = int(child.generate_state(1)[0])
                    columns, metadata = simulate_session(rng, session_seed, duration_s, 1.0 / rate_hz, impaired_share)
                    files.append(str(write_session_log(out, f"session_{index:04d}", columns, metadata)))
                    counts[metadata["patient"]["preset"]] += 1
                    counts["falls"] += len(metadata["falls"])
                    hours += metadata["duration_s"] / 3600.0
                    advance(1)
        except (ParameterError, OSError) as error:
            raise fail(str(error), as_json=as_json) from error
        summary = {"sessions": len(files), **counts, "hours": hours, "out": str(out), "files": files}
        emit(summary, as_json=as_json, human=_print_cohort)

    @app.command("evaluate-falls")
    def evaluate_falls(
        logs: list[Path] = typer.Argument(..., help="Session logs (.npz/.parquet) or directories of them."),
        truth: Path | None = typer.Option(
            None, "--truth", help='JSON {"session": [onset_s, ...]}; default: the falls in each log\'s sidecar.'
        ),
        detectors_file: Path | None = typer.Option(
            None, "--detectors", help="JSON overrides per detector section: harness, cop, unload."
        ),
        body_mass_kg: float | None = typer.Option(None, "--body-mass-kg", help="For logs without a sidecar."),
        before_s: float = typer.Option(1.0, "--window-before-s", help="A detection may precede the onset by this."),
        after_s: float = typer.Option(2.0, "--window-after-s", help="…and follow it by at most this."),
        as_json: bool = typer.Option(False, "--json", help="Print the scores as JSON."),
        plot: Path | None = typer.Option(None, "--plot", help="Directory for PNG plots."),
    ) -> None:
        """Run the fall detectors over logs: latency (median/p95), sensitivity and false alarms per hour."""
        from core.falls import ANY_DETECTOR, DETECTOR_NAMES, MatchingWindow, score_detector
        from core.patient import ParameterError

        try:
            paths = _log_paths(logs)
            window = MatchingWindow(before_s=before_s, after_s=after_s)
            truth_onsets = _load_truth(truth) if truth is not None else None
            overrides = json.loads(detectors_file.read_text()) if detectors_file is not None else {}
            with progress_bar("reading logs", len(paths), enabled=True) as advance:
                labelled, loaded = labelled_logs(paths, truth_onsets, overrides, body_mass_kg, advance)
        except (ParameterError, OSError, ValueError) as error:
            raise fail(str(error), as_json=as_json) from error
        sessions = detections(labelled)
        scores = [score_detector(sessions, name, window) for name in (*DETECTOR_NAMES, ANY_DETECTOR)]
        data: dict[str, Any] = {
            "sessions": len(sessions),
            "hours": sum(s.duration_s for s in sessions) / 3600.0,
            "falls": sum(len(s.fall_onsets_s) for s in sessions),
            "window": {"before_s": window.before_s, "after_s": window.after_s},
            "detectors": [score.to_dict() for score in scores],
            "roc": roc_report(labelled, window, scores),
            "events": {s.name: [_event_summary(e) for e in s.events] for s in sessions},
        }
        if plot is not None:
            data["plots"] = [*_plot(plot, scores, sessions, loaded, window), _plot_roc(plot, data["roc"])]
        emit(data, as_json=as_json, human=_print_scores)

    @app.command("tune-falls")
    def tune_falls(
        logs: list[Path] = typer.Argument(..., help="Training session logs (.npz/.parquet) or directories of them."),
        out: Path | None = typer.Option(None, "--out", help="Write the tuned detector overrides (JSON) here."),
        max_false_alarms_per_hour: float = typer.Option(
            1.0, "--max-false-alarms-per-hour", help="Highest false-alarm rate (per hour) a setting may have."
        ),
        body_mass_kg: float | None = typer.Option(None, "--body-mass-kg", help="For logs without a sidecar."),
        as_json: bool = typer.Option(False, "--json", help="Print the result as JSON."),
    ) -> None:
        """Tune the fused detector's weights, references and threshold on a labelled training cohort."""
        from core.falls import tune_fused
        from core.patient import ParameterError

        try:
            paths = _log_paths(logs)
            with progress_bar("reading logs", len(paths), enabled=True) as advance:
                labelled, _ = labelled_logs(paths, None, {}, body_mass_kg, advance)
            with progress_bar("scoring settings", tuning_combinations(), enabled=True) as advance:
                result = tune_fused(labelled, max_false_alarms_per_hour=max_false_alarms_per_hour, advance=advance)
        except (ParameterError, OSError, ValueError) as error:
            raise fail(str(error), as_json=as_json) from error
        overrides = {"fused": result.settings}
        data: dict[str, Any] = {
            "sessions": len(labelled),
            "hours": sum(log.duration_s for log in labelled) / 3600.0,
            "falls": sum(len(log.fall_onsets_s) for log in labelled),
            "combinations": result.combinations,
            "training": result.training.to_dict(),
            "detectors": overrides,
            "out": None,
        }
        if out is not None:
            out.write_text(json.dumps(overrides, indent=2))
            data["out"] = str(out)
        emit(data, as_json=as_json, human=_print_tuning)


def _plot_roc(directory: Path, roc: dict[str, Any]) -> str:
    """Sensitivity against false alarms per hour per detector, the operating point circled."""
    plt = pyplot()
    figure, axes = plt.subplots(figsize=(7, 5))
    for detector, curve in roc.items():
        points = sorted(curve["points"], key=lambda p: (p["false_alarms_per_hour"], p["sensitivity"]))
        rates = [p["false_alarms_per_hour"] for p in points]
        sensitivities = [100 * p["sensitivity"] for p in points]
        (line,) = axes.plot(rates, sensitivities, marker=".", label=f"{detector} ({curve['parameter']})")
        operating = curve["operating_point"]
        axes.plot(
            operating["false_alarms_per_hour"],
            100 * operating["sensitivity"],
            marker="o",
            markersize=11,
            markerfacecolor="none",
            color=line.get_color(),
        )
    axes.axvline(1.0, color="grey", linestyle=":", label="1 false alarm / h")
    axes.axhline(95.0, color="grey", linestyle="--", label="95 % sensitivity")
    axes.set_xscale("symlog", linthresh=1.0)
    axes.set_xlim(left=0.0)
    axes.set_xlabel("false alarms per hour")
    axes.set_ylabel("sensitivity (%)")
    axes.set_ylim(0, 105)
    axes.set_title("Fall detectors: ROC over their thresholds (circle: operating point)")
    axes.legend(fontsize=7, loc="lower right")
    return str(save_figure(figure, directory, "roc"))


def _print_tuning(data: dict[str, Any]) -> None:
    point = data["training"]
    console.print(
        f"{data['combinations']} combinations on {data['sessions']} sessions ({data['hours']:.2f} h, "
        f"{data['falls']} falls): sensitivity {100 * point['sensitivity']:.0f} %, "
        f"{point['false_alarms_per_hour']:.2f} false alarms/h at threshold {point['threshold']}"
    )
    console.print(f"fused settings: {json.dumps(data['detectors']['fused'])}")
    if data.get("out"):
        console.print(f"written to {data['out']} (pass it to evaluate-falls --detectors)")


def _event_summary(event: FallEvent) -> dict[str, Any]:
    return {"detector": event.detector, "onset_s": event.onset_s, "detected_s": event.detected_s}
