"""C3D export with ezc3d: two force platforms (one per foot), analog channels, events (issue 6 §5).

- Force platforms are C3D TYPE 1 (channels Fx, Fy, Fz, Px, Py, Mz), one per foot plate, right first.
  The plates sense vertical load only, so Fx, Fy and Mz are written as 0 and described as not measured.
  The plate frame is the foot-plate frame (x, y as the platform's, z up): Fz is the vertical ground
  reaction, positive when loaded, and (Px, Py) is the recorded COP. CORNERS are the plate outline in the
  lab frame at the neutral pose; the plates move with the robots, which the PLATE_* points show.
- COP is meaningless on an unloaded plate (REFERENCE.md §5): where Fz < COP_FORCE_THRESHOLD_N, Px and Py
  are NaN and the COP_* points are invalid (residual -1).
- Analogs run at the telemetry rate; points (plate centres and COP in the lab frame, m) at that rate
  divided by an integer ratio, 100 Hz for 1 kHz telemetry, lowered for long sessions because ezc3d
  reads at most 65535 frames. A last partial frame is padded with NaN analog samples.
- Frames are the recorded samples at the nominal rate: a late, skipped or lost tick does not refuse the
  export; the `late` and `tick_gap` analog channels flag it per sample (docs/exports.md).
- Lab frame: the twin's world frame (core/robot.py), metres. Event times are seconds from the first sample.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from pathlib import Path
from typing import Any, BinaryIO

import ezc3d
import numpy as np

from core.kinematics import rotation_matrices, twin_platform_poses
from core.robot import DescriptionError, TwinRobot, twin_from_dict
from server.exports.log import RecordedLog, SessionLog, SessionLogError, to_json
from server.hal.base import FEET

COP_FORCE_THRESHOLD_N = 20.0  # below this a plate carries no foot: COP is noise
DEFAULT_FOOT_PLATE_SIZE_M = (0.40, 0.25)  # x, y; not in the robot description, so a documented default
MAX_C3D_FRAMES = 65535  # 16-bit frame count in the header and POINT:FRAMES
TARGET_POINT_RATE_HZ = 100.0
EVENT_TEXT_MAX = 255  # C3D string dimensions are one byte
COPY_CHUNK_BYTES = 1 << 20
PLATE_CHANNELS = ("Fx", "Fy", "Fz", "Px", "Py", "Mz")  # TYPE 1 channel order
# Channels shown through the force platforms, implicit in the C3D frame numbering, or (POSIX seconds)
# beyond float32 precision.
FIELDS_NOT_AS_ANALOG = ("time_s", "tick", "utc_s", "plate_force_z_n", "plate_cop_m")


def c3d_frame_ratio(sample_rate_hz: float, sample_count: int) -> int:
    """Analog samples per point frame: the smallest ratio giving points at <= 100 Hz, dividing the
    sample rate evenly when it is whole, with at most 65535 frames."""
    smallest = max(1, math.ceil(sample_rate_hz / TARGET_POINT_RATE_HZ), math.ceil(sample_count / MAX_C3D_FRAMES))
    whole_rate = float(sample_rate_hz).is_integer()
    for ratio in range(smallest, max(smallest, int(sample_rate_hz)) + 1):
        if not whole_rate or int(sample_rate_hz) % ratio == 0:
            return ratio
    raise SessionLogError(
        "time_s", sample_count, f"too many samples for one C3D file at {sample_rate_hz} Hz (points at >= 1 Hz)"
    )


def foot_plate_points_world(twin: TwinRobot, side: str, stance_poses: np.ndarray, local_m: np.ndarray) -> np.ndarray:
    """Points given in a foot-plate frame (F, K, 3), or (K, 3) for every frame, in the lab frame (F, K, 3)."""
    positions, rotations = twin_platform_poses(twin, stance_poses)[side]
    placement = twin.placement(side)
    base_yaw = rotation_matrices(np.array([[0.0, 0.0, placement.base_yaw_rad]]))[0]
    in_platform = np.broadcast_to(local_m, (len(positions), *np.shape(local_m)[-2:])) + np.asarray(
        placement.foot_plate_offset_m
    )
    in_base = positions[:, None, :] + np.einsum("fij,fkj->fki", rotations, in_platform)
    return np.asarray(placement.base_origin_m) + in_base @ base_yaw.T


def _twin(log: SessionLog) -> TwinRobot:
    if "robot" not in log.metadata:
        raise SessionLogError("metadata.robot", None, "robot geometry (core.robot.twin_to_dict) is needed for C3D")
    try:
        return twin_from_dict(log.metadata["robot"])
    except DescriptionError as error:
        raise SessionLogError(f"metadata.robot.{error.field}", error.value, error.limit) from error


def _plate_size_m(log: SessionLog) -> tuple[float, float]:
    size = log.metadata.get("foot_plate_size_m", DEFAULT_FOOT_PLATE_SIZE_M)
    if (
        not isinstance(size, list | tuple)
        or len(size) != 2
        or not all(isinstance(v, int | float) and math.isfinite(v) and v > 0 for v in size)
    ):
        raise SessionLogError("metadata.foot_plate_size_m", size, "two lengths (x, y) > 0 in m")
    return float(size[0]), float(size[1])


def _require_finite_stance(stance_pose: np.ndarray) -> None:
    """The plate points are placed from the stance pose, so it must be known at every sample."""
    bad = np.flatnonzero(~np.all(np.isfinite(stance_pose), axis=1))
    if bad.size:
        raise SessionLogError(f"stance_pose[{bad[0]}]", stance_pose[bad[0]].tolist(), "finite numbers for C3D")


def _analog_channels(log: SessionLog) -> list[tuple[str, str, str, np.ndarray]]:
    """(label, unit, description, values) per analog channel: the two plates' TYPE 1 blocks, then the rest."""
    force_z, cop = log.columns["plate_force_z_n"], log.columns["plate_cop_m"]
    zeros = np.zeros(log.sample_count)
    channels = []
    for number, foot in enumerate(FEET, start=1):
        loaded = force_z[:, number - 1] >= COP_FORCE_THRESHOLD_N
        masked_cop = np.where(loaded[:, None], cop[:, number - 1, :], np.nan)
        not_measured = "not measured (plate senses vertical load only), written as 0"
        cop_note = f"{foot} foot-plate frame; NaN where Fz < {COP_FORCE_THRESHOLD_N} N"
        block = (
            ("N", f"{foot} plate Fx: {not_measured}", zeros),
            ("N", f"{foot} plate Fy: {not_measured}", zeros),
            ("N", f"{foot} plate vertical ground reaction, up positive", force_z[:, number - 1]),
            ("m", f"{foot} COP x, {cop_note}", masked_cop[:, 0]),
            ("m", f"{foot} COP y, {cop_note}", masked_cop[:, 1]),
            ("N.m", f"{foot} plate Mz: {not_measured}", zeros),
        )
        channels += [
            (f"{name}{number}", unit, text, values)
            for name, (unit, text, values) in zip(PLATE_CHANNELS, block, strict=True)
        ]
    for channel in log.channels():
        if channel.field in FIELDS_NOT_AS_ANALOG or channel.values.dtype.kind not in "biuf":
            continue
        channels.append((channel.name, channel.unit, f"telemetry {channel.field}", channel.values))
    return channels


def _point_data(
    log: SessionLog, twin: TwinRobot, frame_samples: np.ndarray
) -> tuple[list[str], list[str], np.ndarray, np.ndarray]:
    """Labels, descriptions, points (4, P, F) and residuals (1, P, F): plate centres, then COP per foot."""
    stance = log.columns["stance_pose"][frame_samples].astype(float)
    force_z = log.columns["plate_force_z_n"][frame_samples]
    cop = log.columns["plate_cop_m"][frame_samples].astype(float)
    labels, descriptions, coordinates, valid = [], [], [], []
    for foot in FEET:
        labels.append(f"PLATE_{foot}")
        descriptions.append(f"{foot} foot-plate centre, lab frame")
        coordinates.append(foot_plate_points_world(twin, foot, stance, np.zeros((1, 3)))[:, 0, :])
        valid.append(np.ones(len(frame_samples), dtype=bool))
    for index, foot in enumerate(FEET):
        local = np.concatenate([cop[:, index, :], np.zeros((len(frame_samples), 1))], axis=1)[:, None, :]
        loaded = (force_z[:, index] >= COP_FORCE_THRESHOLD_N) & np.all(np.isfinite(local[:, 0, :]), axis=1)
        labels.append(f"COP_{foot}")
        descriptions.append(f"{foot} centre of pressure, lab frame; invalid where Fz < {COP_FORCE_THRESHOLD_N} N")
        coordinates.append(foot_plate_points_world(twin, foot, stance, np.nan_to_num(local))[:, 0, :])
        valid.append(loaded)
    valid_array = np.array(valid)  # (P, F)
    points = np.ones((4, len(labels), len(frame_samples)))
    points[:3] = np.where(valid_array[None], np.transpose(np.array(coordinates), (2, 0, 1)), np.nan)
    residuals = np.where(valid_array, 0.0, -1.0)[None]
    return labels, descriptions, points, residuals


def _add_int_parameter(c3d: Any, group: str, name: str, values: np.ndarray, description: str = "") -> None:
    """An INTEGER parameter (ezc3d's `add_parameter` stores integer lists as FLOAT)."""
    parameter = ezc3d.ezc3d.Parameter(name, description)
    flat = [int(v) for v in np.asarray(values).reshape(-1, order="F")]
    parameter.set(ezc3d.ezc3d.VecInt(flat), list(np.shape(values)))
    c3d["parameters"].add_parameter(group, parameter)


def _add_force_platforms(c3d: Any, twin: TwinRobot, plate_size_m: tuple[float, float]) -> None:
    half_x, half_y = plate_size_m[0] / 2.0, plate_size_m[1] / 2.0
    # C3D corner order: the plate's +x+y, -x+y, -x-y, +x-y quadrants.
    local_corners = np.array(
        [[half_x, half_y, 0.0], [-half_x, half_y, 0.0], [-half_x, -half_y, 0.0], [half_x, -half_y, 0.0]]
    )
    neutral = np.zeros((1, 6))
    corners = np.stack([foot_plate_points_world(twin, foot, neutral, local_corners)[0].T for foot in FEET], axis=2)
    plate_count = len(FEET)
    channel_numbers = np.arange(1, len(PLATE_CHANNELS) * plate_count + 1).reshape(plate_count, -1).T
    _add_int_parameter(c3d, "FORCE_PLATFORM", "USED", np.array([plate_count]))
    _add_int_parameter(c3d, "FORCE_PLATFORM", "TYPE", np.ones(plate_count), "TYPE 1: Fx Fy Fz Px Py Mz")
    _add_int_parameter(c3d, "FORCE_PLATFORM", "ZERO", np.zeros(2), "no baseline correction: already zeroed")
    _add_int_parameter(c3d, "FORCE_PLATFORM", "CHANNEL", channel_numbers, "1-based analog channel numbers")
    c3d.add_parameter("FORCE_PLATFORM", "CORNERS", corners, "plate outline in the lab frame at the neutral pose, m")
    c3d.add_parameter("FORCE_PLATFORM", "ORIGIN", np.zeros((3, plate_count)), "plate frame origin at its top centre")


def _ascii(text: str) -> str:
    clean = text.encode("ascii", "replace").decode()
    return clean if len(clean) <= EVENT_TEXT_MAX else clean[: EVENT_TEXT_MAX - 3] + "..."


def _add_events(c3d: Any, log: SessionLog, subject: str) -> None:
    start_s = float(log.columns["time_s"][0])
    for event in log.events:
        seconds = event["tick_time_s"] - start_s
        minutes = math.floor(seconds / 60.0)
        side = event["details"].get("foot") or event["details"].get("side")
        context = side.capitalize() if side in FEET else "General"
        description = f"detector={event['detector'] or 'none'} tick={event['tick']} {to_json(event['details'])}"
        c3d.add_event(
            [minutes, seconds - 60.0 * minutes],
            context=context,
            label=_ascii(event["kind"]),
            description=_ascii(description),
            subject=subject,
        )


def _add_session_parameters(c3d: Any, log: SessionLog, padded_samples: int) -> str:
    patient = log.metadata.get("patient") or {}
    subject = str(patient.get("pseudonym_id", ""))
    software = log.metadata.get("software") or {}
    c3d.add_parameter("SUBJECTS", "NAMES", [subject], "pseudonymised patient id")
    _add_int_parameter(c3d, "SUBJECTS", "USED", np.array([1]))
    c3d.add_parameter("MANUFACTURER", "COMPANY", "ssp-rehab")
    c3d.add_parameter("MANUFACTURER", "SOFTWARE", str(software.get("name", "ssp-rehab")))
    c3d.add_parameter("MANUFACTURER", "VERSION_LABEL", str(software.get("version", "unknown")))
    group = "SSP_REHAB"
    c3d.add_parameter(group, "SESSION_ID", log.session_id)
    # Ticks and monotonic seconds exceed float32 precision: kept as text.
    c3d.add_parameter(group, "FIRST_TICK", str(int(log.columns["tick"][0])), "tick of the first analog sample")
    c3d.add_parameter(group, "FIRST_TIME_S", repr(float(log.columns["time_s"][0])), "monotonic time, first sample")
    c3d.add_parameter(group, "COP_THRESHOLD_N", COP_FORCE_THRESHOLD_N, "COP invalid below this plate Fz")
    _add_int_parameter(c3d, group, "PADDED_SAMPLES", np.array([padded_samples]), "NaN analog samples at the end")
    return subject


def write_c3d(recorded: RecordedLog, sink: BinaryIO) -> None:
    """The session as a C3D file (see the module docstring for the conventions). ezc3d holds the whole file,
    so this is the one export whose memory grows with the run (docs/exports.md)."""
    log = recorded.whole()
    twin = _twin(log)
    plate_size_m = _plate_size_m(log)
    _require_finite_stance(log.columns["stance_pose"])
    sample_rate_hz = log.sample_rate_hz
    ratio = c3d_frame_ratio(sample_rate_hz, log.sample_count)
    frame_count = math.ceil(log.sample_count / ratio)
    padded_samples = frame_count * ratio - log.sample_count

    c3d = ezc3d.c3d()
    analog = _analog_channels(log)
    analog_data = np.full((1, len(analog), frame_count * ratio), np.nan)
    analog_data[0, :, : log.sample_count] = np.array([values for *_, values in analog], dtype=float)
    c3d["parameters"]["ANALOG"]["RATE"]["value"] = [sample_rate_hz]
    c3d["parameters"]["ANALOG"]["LABELS"]["value"] = [label for label, *_ in analog]
    c3d["parameters"]["ANALOG"]["UNITS"]["value"] = [unit for _, unit, *_ in analog]
    c3d["parameters"]["ANALOG"]["DESCRIPTIONS"]["value"] = [text for _, _, text, _ in analog]
    c3d["parameters"]["ANALOG"]["SCALE"]["value"] = [1.0] * len(analog)
    c3d["parameters"]["ANALOG"]["GEN_SCALE"]["value"] = [1.0]
    c3d["data"]["analogs"] = analog_data

    labels, descriptions, points, residuals = _point_data(log, twin, np.arange(frame_count) * ratio)
    c3d["parameters"]["POINT"]["RATE"]["value"] = [sample_rate_hz / ratio]
    c3d["parameters"]["POINT"]["UNITS"]["value"] = ["m"]
    c3d["parameters"]["POINT"]["LABELS"]["value"] = labels
    c3d["parameters"]["POINT"]["DESCRIPTIONS"]["value"] = descriptions
    c3d["data"]["points"] = points
    c3d["data"]["meta_points"] = {
        "residuals": residuals,
        "camera_masks": np.zeros((7, len(labels), frame_count), dtype=bool),
    }

    _add_force_platforms(c3d, twin, plate_size_m)
    subject = _add_session_parameters(c3d, log, padded_samples)
    _add_events(c3d, log, subject)
    with tempfile.TemporaryDirectory(prefix="ssp-rehab-c3d-") as directory:
        path = Path(directory) / "session.c3d"
        c3d.write(str(path))
        with path.open("rb") as written:
            shutil.copyfileobj(written, sink, COPY_CHUNK_BYTES)
