"""The PDF layout (reportlab platypus, matplotlib charts as PNG): a run report and a progress report.
Lengths in mm, areas in cm², angles in degrees, as on the console's screens."""

from __future__ import annotations

import datetime as dt
import io
import math
from collections.abc import Sequence
from typing import Any

import matplotlib

matplotlib.use("Agg")  # no display on the service machine
from xml.sax.saxutils import escape

import matplotlib.pyplot as plt
import numpy as np
from reportlab.lib import colors
from reportlab.lib.pagesizes import A4
from reportlab.lib.styles import getSampleStyleSheet
from reportlab.lib.units import cm
from reportlab.platypus import Image, Paragraph, SimpleDocTemplate, Spacer, Table, TableStyle

from server.reports.facts import ProgressRow, RunFacts
from server.sessions.balance import MIN_WINDOW_S

STYLES = getSampleStyleSheet()
OUTCOME_WORDS = {
    "completed": "completed",
    "stopped": "stopped by the therapist",
    "emergency_stop": "emergency stop",
    "fall": "fall detected",
    "fault": "fault",
    "limit_hit": "stopped at a robot limit",
}
FAULTED = frozenset({"fall", "fault", "limit_hit", "emergency_stop"})
# A detail's unit from its name's SI suffix: (suffix, unit shown, factor, digits).
UNIT_SUFFIXES = (
    ("_m_s2", "m/s²", 1.0, 2),
    ("_rad_s", "°/s", 180 / math.pi, 1),
    ("_rad", "°", 180 / math.pi, 1),
    ("_m_s", "mm/s", 1000.0, 0),
    ("_m2", "cm²", 1e4, 1),
    ("_m", "mm", 1000.0, 0),
    ("_n", "N", 1.0, 0),
    ("_kg", "kg", 1.0, 1),
    ("_hz", "Hz", 1.0, 2),
    ("_s", "s", 1.0, 2),
)
SWAY_ROWS = (
    ("rms_distance_m", "RMS distance", "mm", 1000.0, 1),
    ("rms_ap_m", "RMS, anterior–posterior", "mm", 1000.0, 1),
    ("rms_ml_m", "RMS, medio-lateral", "mm", 1000.0, 1),
    ("mean_velocity_m_s", "Mean velocity", "mm/s", 1000.0, 1),
    ("path_length_m", "Path length", "mm", 1000.0, 0),
    ("ellipse_area_95_m2", "95 % ellipse area", "cm²", 1e4, 2),
    ("duration_s", "Duration analysed", "s", 1.0, 1),
    ("window_from_s", "Window analysed, from (into the run)", "s", 1.0, 1),
    ("window_to_s", "Window analysed, to (into the run)", "s", 1.0, 1),
)


def words(name: object) -> str:
    return str(name or "").replace("_", " ")


def detail_words(details: dict[str, Any]) -> str:
    parts = []
    for key, value in details.items():
        if value is None or value == "" or key in {"tick_from_utc", "prescription_version_id"}:
            continue
        suffix = next((s for s in UNIT_SUFFIXES if key.endswith(s[0])), None)
        if suffix is not None and isinstance(value, int | float) and not isinstance(value, bool):
            end, unit, factor, digits = suffix
            parts.append(f"{words(key[: -len(end)])} {value * factor:.{digits}f} {unit}")
        elif not isinstance(value, dict | list):
            parts.append(f"{words(key)}: {words(value) if isinstance(value, str) else value}")
    return ", ".join(parts)


def _p(text: str, style: str = "BodyText") -> Paragraph:
    return Paragraph(escape(text).replace("\n", "<br/>"), STYLES[style])


def _table(rows: Sequence[Sequence[Any]], widths: Sequence[float] | None = None) -> Table:
    cells = [[_p(str(cell)) if not isinstance(cell, Paragraph) else cell for cell in row] for row in rows]
    table = Table(cells, colWidths=widths, repeatRows=1)
    table.setStyle(
        TableStyle(
            [
                ("BACKGROUND", (0, 0), (-1, 0), colors.HexColor("#e4e8ee")),
                ("GRID", (0, 0), (-1, -1), 0.4, colors.HexColor("#8a8a8a")),
                ("VALIGN", (0, 0), (-1, -1), "TOP"),
            ]
        )
    )
    return table


def _figure_image(figure: Any, width_cm: float = 17.0) -> Image:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
    plt.close(figure)
    buffer.seek(0)
    width_px, height_px = figure.get_size_inches() * 110
    return Image(buffer, width=width_cm * cm, height=width_cm * cm * height_px / width_px)


def _fmt(value: float | None, unit: str, digits: int = 1, factor: float = 1.0) -> str:
    return "—" if value is None or not math.isfinite(value) else f"{value * factor:.{digits}f} {unit}"


def _local(moment: dt.datetime | None) -> str:
    return "—" if moment is None else moment.astimezone().strftime("%Y-%m-%d %H:%M:%S %Z")


def _cue_rows(content: dict[str, Any]) -> list[list[str]]:
    rows = [["Segment", "Cue", "Settings", "Duration"]]
    for number, segment in enumerate(content.get("segments", []), start=1):
        cue = dict(segment.get("cue", {}))
        kind = cue.pop("kind", "?")
        if "csv" in cue:
            cue["csv"] = f"{len(str(cue['csv']).strip().splitlines()) - 1} recorded rows"
        if "components" in cue:
            cue["components"] = "; ".join(detail_words(c) for c in cue["components"])
        rows.append([str(number), words(kind), detail_words(cue), _fmt(segment.get("duration_s"), "s", 0)])
    return rows


def run_report_pdf(facts: RunFacts) -> bytes:
    run, patient = facts.run, facts.patient
    story: list[Any] = [
        _p(f"Session report: run {run.id}", "Title"),
        _table(
            [
                ["Patient", "Record number", "Date of birth", "Sex", "Height", "Body mass"],
                [
                    patient.name,
                    patient.identifier,
                    str(patient.date_of_birth),
                    patient.sex,
                    _fmt(patient.height_m, "cm", 0, 100),
                    _fmt(patient.body_mass_kg, "kg", 1),
                ],
            ]
        ),
        Spacer(1, 6),
        _table(
            [
                ["Run", "Robot", "Started", "Ended", "Duration", "Outcome"],
                [
                    str(run.id),
                    run.robot,
                    _local(run.started_at),
                    _local(run.ended_at),
                    _fmt(facts.duration_s, "s", 1),
                    OUTCOME_WORDS.get(run.outcome or "", words(run.outcome or run.state)),
                ],
            ]
        ),
        _p(
            f"Diagnosis: {patient.diagnosis or '—'}. Affected side: {patient.affected_side}. "
            f"Contraindications: {patient.contraindications or 'none recorded'}."
        ),
        _p(f"Prescription: {facts.prescription_name}, version {facts.version.version}", "Heading2"),
        _table(_cue_rows(facts.version.content), [2 * cm, 3.5 * cm, 9 * cm, 2.5 * cm]),
    ]
    story += [_p("Outcome and events (time into the run)", "Heading2")]
    event_rows = [["Time into the run", "Event", "What happened"]]
    for event in facts.events:
        details = {
            **({"detector": event.detector} if event.detector and event.detector != "console" else {}),
            **event.details,
        }
        event_rows.append([_fmt(event.time_into_run_s, "s", 1), words(event.kind), detail_words(details) or "—"])
    story.append(_table(event_rows, [3.5 * cm, 4 * cm, 9.5 * cm]) if len(event_rows) > 1 else _p("No events."))
    falls = facts.falls
    story.append(
        _p(
            "Falls: none."
            if not falls
            else "Falls: "
            + "; ".join(f"at {_fmt(f.time_into_run_s, 's', 1)} into the run ({words(f.detector)})" for f in falls)
            + "."
        )
    )
    acknowledgement = facts.review.acknowledgement
    if acknowledgement is not None:
        story.append(
            _p(
                f"Acknowledged by {facts.user_names.get(acknowledgement.user_id or 0, 'a deleted account')} at "
                f"{_local(acknowledgement.utc)}: {acknowledgement.note}"
            )
        )
    elif facts.review.needs_acknowledgement:
        story.append(
            _p("Not yet acknowledged: the robot starts again only after the therapist acknowledges this stop.")
        )

    story.append(_p("Balance (Prieto 1996 sway measures of the net centre of pressure)", "Heading2"))
    if facts.sway:
        story.append(
            _table(
                [["Measure", "Value"]]
                + [
                    [label, _fmt(facts.sway.get(key), unit, digits, factor)]
                    for key, label, unit, factor, digits in SWAY_ROWS
                ]
            )
        )
    else:
        story.append(
            _p(
                f"Not measured: the sway measures need at least {MIN_WINDOW_S:g} s of the run in motion with the feet "
                "on the plates, and this run had less."
            )
        )
    story.append(_p("Cue quality (perceived through the otolith model, paper §4.2)", "Heading2"))
    quality = facts.cue_quality
    if quality:
        rows = [["Axis", "Cue RMS", "Perceived error RMS", "Perceived error peak", "Correlation cue/platform"]]
        for axis in ("x", "y", "z"):
            corr = quality["correlation"].get(axis)
            rows.append(
                [
                    axis,
                    _fmt(quality["cue_rms_m_s2"][axis], "m/s²", 3),
                    _fmt(quality["perceived_error_rms_m_s2"][axis], "m/s²", 3),
                    _fmt(quality["perceived_error_peak_m_s2"][axis], "m/s²", 3),
                    "—" if corr is None else f"{corr:.2f}",
                ]
            )
        story.append(_table(rows))
        story.append(
            _p(
                f"Perception error: {quality['perception_error_thresholds']:.2f} "
                "(sum of RMS errors in perception thresholds; lower is better)."
            )
        )
    else:
        story.append(_p("Not enough telemetry for the cue quality."))
    story += _run_charts(facts)
    notes = facts.review.notes
    author = facts.user_names.get(notes.author_id or 0)
    story.append(_p(f"Therapist notes (SOAP){f', by {author}' if author else ''}", "Heading2"))
    story.append(
        _table(
            [
                ["", "Note"],
                ["S: subjective", notes.subjective or "—"],
                ["O: objective", notes.objective or "—"],
                ["A: assessment", notes.assessment or "—"],
                ["P: plan", notes.plan or "—"],
            ],
            [3.5 * cm, 13.5 * cm],
        )
    )
    return _build(story, f"ssp-rehab run {run.id}")


def _run_charts(facts: RunFacts) -> list[Any]:
    series = facts.series
    if not series:
        return []
    t = series["time_s"]
    figure, axes = plt.subplots(3, 1, figsize=(8, 7.5), sharex=True)
    cop = series["cop_m"] * 1000.0
    for foot, name in ((0, "right"), (1, "left")):
        axes[0].plot(t, cop[:, foot, 0], label=f"{name} AP")
        axes[0].plot(t, cop[:, foot, 1], "--", label=f"{name} ML")
    axes[0].set_ylabel("COP (mm)")
    axes[0].set_title("Centre of pressure, each foot")
    for index, axis in enumerate(("x", "y")):
        axes[1].plot(t, series["cue_m_s2"][:, index], "--", label=f"cue {axis}")
        if "delivered_m_s2" in series:
            axes[1].plot(t, series["delivered_m_s2"][:, index], label=f"platform {axis}")
    axes[1].set_ylabel("specific force (m/s²)")
    axes[1].set_title("Cue: commanded (dashed) and delivered by the platform")
    axes[2].plot(t, series["harness_load_n"], color="#b00020", label="harness")
    axes[2].plot(t, series["plate_force_z_n"][:, 0], label="right plate Fz")
    axes[2].plot(t, series["plate_force_z_n"][:, 1], label="left plate Fz")
    axes[2].set_ylabel("force (N)")
    axes[2].set_xlabel("time into the run (s)")
    axes[2].set_title("Harness load and foot-plate forces")
    for fall in facts.falls:
        if fall.time_into_run_s is not None:
            for axis in axes:
                axis.axvline(fall.time_into_run_s, color="#ff8f00", linewidth=2)
    for axis in axes:
        axis.grid(alpha=0.3)
        axis.legend(fontsize=7, loc="upper right", ncols=3)
    figure.tight_layout()
    return [_p("Charts (orange lines: falls)", "Heading2"), _figure_image(figure)]


def progress_report_pdf(patient: Any, rows: list[ProgressRow], start: dt.date | None, end: dt.date | None) -> bytes:
    period = f"{start or 'first run'} to {end or 'today'}"
    story: list[Any] = [
        _p(f"Progress report: {patient.name} ({patient.identifier})", "Title"),
        _p(
            f"Runs from {period}: {len(rows)}. Faulted runs (fall, fault, limit stop, emergency stop) are "
            "marked ✕ in the charts and the table."
        ),
    ]
    table = [
        [
            "Date",
            "Prescription",
            "Outcome",
            "Falls",
            "RMS distance",
            "Mean velocity",
            "95 % ellipse",
            "Perception error",
        ]
    ]
    for row in rows:
        sway = row.sway or {}
        table.append(
            [
                row.run.started_at.astimezone().strftime("%Y-%m-%d %H:%M"),
                f"{row.prescription_name} v{row.version}",
                ("✕ " if row.run.outcome in FAULTED else "")
                + OUTCOME_WORDS.get(row.run.outcome or "", words(row.run.outcome)),
                str(row.falls),
                _fmt(sway.get("rms_distance_m"), "mm", 1, 1000),
                _fmt(sway.get("mean_velocity_m_s"), "mm/s", 1, 1000),
                _fmt(sway.get("ellipse_area_95_m2"), "cm²", 2, 1e4),
                _fmt(row.perception_error, "", 2),
            ]
        )
    story.append(_table(table) if rows else _p("No runs in this period."))
    if rows:
        story.append(_progress_charts(rows))
    return _build(story, f"ssp-rehab progress {patient.identifier}")


def _progress_charts(rows: list[ProgressRow]) -> Image:
    """One measure per chart, one unit per axis, by date; faulted runs marked ✕."""
    dates = [row.run.started_at for row in rows]
    faulted = np.array([row.run.outcome in FAULTED for row in rows])
    panels = (
        ("RMS distance (mm)", [row.sway["rms_distance_m"] * 1000 if row.sway else np.nan for row in rows]),
        ("Mean COP velocity (mm/s)", [row.sway["mean_velocity_m_s"] * 1000 if row.sway else np.nan for row in rows]),
        ("95 % ellipse area (cm²)", [row.sway["ellipse_area_95_m2"] * 1e4 if row.sway else np.nan for row in rows]),
        ("Falls (count)", [row.falls for row in rows]),
    )
    figure, axes = plt.subplots(len(panels), 1, figsize=(8, 9), sharex=True)
    for axis, (label, values) in zip(axes, panels, strict=True):
        values = np.asarray(values, dtype=float)
        axis.plot(dates, values, "o-", color="#0b4fa8")
        if faulted.any():
            axis.plot(
                np.asarray(dates, dtype=object)[faulted],
                values[faulted],
                "x",
                color="#b00020",
                markersize=10,
                label="faulted run",
            )
            axis.legend(fontsize=7)
        axis.set_ylabel(label)
        axis.grid(alpha=0.3)
    axes[-1].set_xlabel("date")
    figure.autofmt_xdate()
    figure.tight_layout()
    return _figure_image(figure)


def _build(story: list[Any], title: str) -> bytes:
    buffer = io.BytesIO()
    document = SimpleDocTemplate(
        buffer,
        pagesize=A4,
        title=title,
        author="ssp-rehab",
        leftMargin=2 * cm,
        rightMargin=2 * cm,
        topMargin=1.6 * cm,
        bottomMargin=1.6 * cm,
    )
    document.build(story)
    return buffer.getvalue()
