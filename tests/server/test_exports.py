"""Session-log exports (issue 6 §5): every file is read back and checked; the C3D with ezc3d."""

from __future__ import annotations

import csv
import datetime as dt
import io
import json
import math
import zipfile
from pathlib import Path

import ezc3d
import numpy as np
import pyarrow.parquet as pq
import pytest

from core.kinematics import twin_inverse_kinematics
from core.robot import TwinRobot, twin_to_dict
from server.exports import (
    SessionLog,
    SessionLogError,
    export_bundle,
    export_session,
    pseudonymise,
    session_log_from_json,
    session_metadata,
)
from server.exports.c3d import COP_FORCE_THRESHOLD_N, DEFAULT_FOOT_PLATE_SIZE_M, c3d_frame_ratio
from server.exports.log import REQUIRED_COLUMNS
from server.exports.metadata import software_version
from server.realtime.telemetry import TELEMETRY_DTYPE, SupervisorState

SAMPLE_RATE_HZ = 1000.0
SAMPLE_COUNT = 3005  # not a multiple of the C3D frame ratio (10): exercises the padded last frame
FIRST_TICK = 5000
FIRST_TIME_S = 12.5
SALT = "study-salt-0123456789abcdef"
STARTED_UTC = dt.datetime(2024, 3, 1, 9, 30, tzinfo=dt.UTC)
PATIENT = {
    "identifier": "MRN-0042917",
    "name": "Jane Quinta Example",
    "date_of_birth": "1961-07-15",
    "sex": "female",
    "height_m": 1.68,
    "body_mass_kg": 64.0,
    "diagnosis": "vestibular hypofunction",
    "affected_side": "left",
    "notes": "lives with her daughter Mary Example",
}
LEFT_UNLOADED = slice(1000, 1500)  # the left foot lifts off: its COP is meaningless there
FALL_TICK = FIRST_TICK + 2500


def synthetic_columns(twin: TwinRobot, sample_count: int = SAMPLE_COUNT) -> dict[str, np.ndarray]:
    """A sine-driven fake session at 1 kHz: sway of the stance frame, IK slider positions, two loaded plates."""
    samples = np.arange(sample_count)
    time_s = FIRST_TIME_S + samples / SAMPLE_RATE_HZ
    phase = 2.0 * np.pi * 0.5 * (time_s - FIRST_TIME_S)
    stance_pose = np.zeros((sample_count, 6))
    stance_pose[:, 1] = 0.02 * np.sin(phase)
    stance_pose[:, 3] = 0.05 * np.sin(phase)
    solutions = twin_inverse_kinematics(twin, stance_pose)
    slider_position_m = np.concatenate([solutions["right"].slider_positions_m, solutions["left"].slider_positions_m], 1)
    cue_force = np.zeros((sample_count, 3))
    cue_force[:, 1] = 0.5 * np.sin(phase)
    cue_rate = np.zeros((sample_count, 3))
    cue_rate[:, 0] = 0.1 * np.cos(phase)
    plate_force_z = np.stack([400.0 + 100.0 * np.sin(phase), 300.0 - 100.0 * np.sin(phase)], axis=1)
    plate_force_z[LEFT_UNLOADED, 1] = 3.0
    plate_cop = np.stack(
        [
            np.stack([0.02 * np.sin(phase), 0.01 * np.cos(phase)], axis=1),
            np.stack([-0.015 * np.sin(phase), 0.012 * np.cos(phase)], axis=1),
        ],
        axis=1,
    )
    plate_cop[LEFT_UNLOADED, 1, :] = 0.19  # what an unloaded plate's COP computation gives: noise at the rim
    harness_load = 30.0 + 5.0 * np.sin(3.0 * phase)
    harness_load[FALL_TICK - FIRST_TICK :] = 320.0
    return {
        "tick": FIRST_TICK + samples.astype(np.int64),
        "time_s": time_s,
        "state": np.full(sample_count, 3, dtype=np.uint8),
        "cue_specific_force_m_s2": cue_force,
        "cue_angular_velocity_rad_s": cue_rate,
        "stance_pose": stance_pose,
        "slider_command_m": slider_position_m + 1e-5,
        "slider_position_m": slider_position_m,
        "drive_force_n": 900.0 + 300.0 * np.sin(phase[:, None] + np.arange(12)[None, :]),
        "plate_force_z_n": plate_force_z,
        "plate_cop_m": plate_cop,
        "harness_load_n": harness_load,
        "tick_compute_us": (80.0 + 10.0 * np.sin(phase)).astype(np.float32),
        "lateness_us": np.abs(5.0 * np.cos(phase)).astype(np.float32),
    }


def synthetic_events() -> list[dict]:
    return [
        {
            "kind": "pause",
            "tick": FIRST_TICK + 500,
            "tick_time_s": FIRST_TIME_S + 0.5,
            "utc": "2024-03-01T09:30:00.500+00:00",
            "detector": None,
            "details": {"by": "therapist"},
        },
        {
            "kind": "fall",
            "tick": FALL_TICK,
            "tick_time_s": FIRST_TIME_S + 2.5,
            "utc": "2024-03-01T09:30:02.500+00:00",
            "detector": "harness_load",
            "details": {"load_n": 320.0, "threshold_n": 188.3, "foot": "left"},
        },
    ]


def metadata_for(twin: TwinRobot, session_id: str = "41", patient: dict | None = None, **overrides) -> dict:
    return session_metadata(
        session_id=session_id,
        started_utc=overrides.pop("started_utc", STARTED_UTC),
        sample_rate_hz=SAMPLE_RATE_HZ,
        patient=patient or PATIENT,
        prescription={"segments": [{"cue": {"kind": "sine"}, "duration_s": 3.0, "washout": {"k_tilt": 0.8}}]},
        prescription_version=3,
        twin=twin,
        salt=SALT,
        **overrides,
    )


@pytest.fixture(scope="module")
def columns(twin: TwinRobot) -> dict[str, np.ndarray]:
    return synthetic_columns(twin)


@pytest.fixture(scope="module")
def log(twin: TwinRobot, columns: dict[str, np.ndarray]) -> SessionLog:
    return SessionLog(columns=columns, events=synthetic_events(), metadata=metadata_for(twin))


@pytest.fixture(scope="module")
def c3d_file(log: SessionLog, tmp_path_factory: pytest.TempPathFactory) -> ezc3d.c3d:
    data, media_type, filename = export_session(log, "c3d")
    assert (media_type, filename) == ("application/octet-stream", "session-41.c3d")
    path = tmp_path_factory.mktemp("c3d") / filename
    path.write_bytes(data)
    return ezc3d.c3d(str(path), extract_forceplat_data=True)


def c3d_parameter(c3d: ezc3d.c3d, group: str, name: str):
    return c3d["parameters"][group][name]["value"]


# --- CSV -------------------------------------------------------------------------------------------


def test_csv_zip_holds_telemetry_with_units_in_headers_and_exact_values(log, columns):
    data, media_type, filename = export_session(log, "csv")
    assert (media_type, filename) == ("application/zip", "session-41-csv.zip")
    archive = zipfile.ZipFile(io.BytesIO(data))
    assert sorted(archive.namelist()) == ["events.csv", "metadata.json", "telemetry.csv"]
    rows = list(csv.reader(io.StringIO(archive.read("telemetry.csv").decode())))
    header, body = rows[0], rows[1:]
    assert header[0] == "time [s]"
    expected_headers = {
        "slider_position_right_1 [m]",
        "slider_position_left_6 [m]",
        "drive_force_right_3 [N]",
        "stance_pose_roll [rad]",
        "stance_pose_y [m]",
        "cue_specific_force_y [m/s^2]",
        "cue_angular_velocity_x [rad/s]",
        "plate_force_z_left [N]",
        "plate_cop_left_y [m]",
        "harness_load [N]",
        "tick",
        "lateness [us]",
    }
    assert expected_headers <= set(header)
    assert len(body) == SAMPLE_COUNT
    table = np.array(body)

    def column(name: str) -> np.ndarray:
        return table[:, header.index(name)]

    np.testing.assert_array_equal(column("time [s]").astype(float), columns["time_s"])
    np.testing.assert_array_equal(column("tick").astype(int), columns["tick"])
    np.testing.assert_array_equal(
        column("slider_position_left_4 [m]").astype(float), columns["slider_position_m"][:, 9]
    )
    np.testing.assert_array_equal(column("plate_cop_right_y [m]").astype(float), columns["plate_cop_m"][:, 0, 1])
    np.testing.assert_array_equal(column("stance_pose_roll [rad]").astype(float), columns["stance_pose"][:, 3])


def test_csv_events_and_sidecar_describe_the_session(log):
    archive = zipfile.ZipFile(io.BytesIO(export_session(log, "csv")[0]))
    events = list(csv.DictReader(io.StringIO(archive.read("events.csv").decode())))
    assert [e["kind"] for e in events] == ["pause", "fall"]
    assert events[1]["detector"] == "harness_load"
    assert int(events[1]["tick"]) == FALL_TICK
    assert float(events[1]["tick_time [s]"]) == FIRST_TIME_S + 2.5
    assert json.loads(events[1]["details"])["load_n"] == 320.0
    sidecar = json.loads(archive.read("metadata.json"))
    assert sidecar["recording"]["channels"]["slider_position_right_1"] == {"unit": "m", "field": "slider_position_m"}
    assert sidecar["recording"]["channels"]["stance_pose_yaw"]["unit"] == "rad"
    assert sidecar["prescription"]["version"] == 3
    assert sidecar["washout_parameters"] == [{"k_tilt": 0.8}]
    assert sidecar["robot"]["robot"]["rod_length_m"] == 1.0
    assert sidecar["software"]["version"] == software_version()
    assert sidecar["sample_rate_hz"] == SAMPLE_RATE_HZ


# --- Parquet ---------------------------------------------------------------------------------------


def test_parquet_schema_units_metadata_and_values(log, columns):
    data, media_type, filename = export_session(log, "parquet")
    assert (media_type, filename) == ("application/vnd.apache.parquet", "session-41.parquet")
    table = pq.read_table(io.BytesIO(data))
    assert table.num_rows == SAMPLE_COUNT
    assert table.schema.names[0] == "time"
    assert table.schema.field("drive_force_left_2").metadata[b"unit"] == b"N"
    assert table.schema.field("cue_specific_force_z").metadata[b"unit"] == b"m/s^2"
    assert table.schema.field("plate_cop_left_x").metadata[b"field"] == b"plate_cop_m"
    assert str(table.schema.field("tick").type) == "int64"
    assert str(table.schema.field("lateness").type) == "float"  # float32 kept
    metadata = json.loads(table.schema.metadata[b"ssp_rehab.metadata"])
    events = json.loads(table.schema.metadata[b"ssp_rehab.events"])
    assert metadata["session_id"] == "41"
    assert metadata["recording"]["fields"]["plate_cop_m"] == {"dtype": "float64", "shape": [2, 2]}
    assert [e["detector"] for e in events] == [None, "harness_load"]
    np.testing.assert_array_equal(table.column("drive_force_left_2").to_numpy(), columns["drive_force_n"][:, 7])
    np.testing.assert_array_equal(table.column("harness_load").to_numpy(), columns["harness_load_n"])
    np.testing.assert_array_equal(table.column("state").to_numpy(), columns["state"])


# --- JSON ------------------------------------------------------------------------------------------


def test_json_round_trip_keeps_columns_events_metadata_and_nan(twin, columns):
    with_nan = dict(columns, plate_cop_m=columns["plate_cop_m"].copy())
    with_nan["plate_cop_m"][LEFT_UNLOADED, 1, :] = np.nan
    original = SessionLog(columns=with_nan, events=synthetic_events(), metadata=metadata_for(twin))
    data, media_type, filename = export_session(original, "json")
    assert (media_type, filename) == ("application/json", "session-41.json")

    def refuse_non_standard(token: str) -> None:
        raise AssertionError(f"{token} is not JSON: standard parsers refuse it")

    document = json.loads(data, parse_constant=refuse_non_standard)
    assert set(document) == {"metadata", "events", "columns"}
    restored = session_log_from_json(data)
    assert restored.columns.keys() == original.columns.keys()
    for name, values in original.columns.items():
        assert restored.columns[name].dtype == values.dtype, name
        np.testing.assert_array_equal(restored.columns[name], values, err_msg=name)
    assert restored.events == original.events
    assert restored.metadata == json.loads(json.dumps(original.metadata))


# --- C3D -------------------------------------------------------------------------------------------


def test_c3d_rates_are_consistent_and_last_frame_is_padded(c3d_file, columns):
    assert c3d_parameter(c3d_file, "ANALOG", "RATE")[0] == SAMPLE_RATE_HZ
    assert c3d_parameter(c3d_file, "POINT", "RATE")[0] == 100.0
    analogs = c3d_file["data"]["analogs"]
    frames = c3d_file["data"]["points"].shape[2]
    assert frames == math.ceil(SAMPLE_COUNT / 10)
    assert analogs.shape[2] == frames * 10
    labels = c3d_parameter(c3d_file, "ANALOG", "LABELS")
    harness = analogs[0, labels.index("harness_load")]
    np.testing.assert_allclose(harness[:SAMPLE_COUNT], columns["harness_load_n"], rtol=1e-6)
    assert np.all(np.isnan(harness[SAMPLE_COUNT:]))
    assert int(c3d_parameter(c3d_file, "SSP_REHAB", "PADDED_SAMPLES")[0]) == frames * 10 - SAMPLE_COUNT


def test_c3d_analog_channels_carry_units_and_the_recorded_values(c3d_file, columns):
    labels = c3d_parameter(c3d_file, "ANALOG", "LABELS")
    units = dict(zip(labels, c3d_parameter(c3d_file, "ANALOG", "UNITS"), strict=True))
    assert labels[:12] == ["Fx1", "Fy1", "Fz1", "Px1", "Py1", "Mz1", "Fx2", "Fy2", "Fz2", "Px2", "Py2", "Mz2"]
    assert units["Fz1"] == "N" and units["Px2"] == "m" and units["Mz1"] == "N.m"
    assert units["slider_position_right_1"] == "m" and units["drive_force_left_6"] == "N"
    assert units["cue_specific_force_y"] == "m/s^2" and units["stance_pose_pitch"] == "rad"
    assert np.all(c3d_parameter(c3d_file, "ANALOG", "SCALE") == 1.0)
    analogs = c3d_file["data"]["analogs"][0, :, :SAMPLE_COUNT]
    np.testing.assert_allclose(analogs[labels.index("Fz1")], columns["plate_force_z_n"][:, 0], rtol=1e-6)
    np.testing.assert_allclose(analogs[labels.index("Fz2")], columns["plate_force_z_n"][:, 1], rtol=1e-6)
    np.testing.assert_allclose(
        analogs[labels.index("slider_position_left_3")], columns["slider_position_m"][:, 8], rtol=1e-6
    )
    np.testing.assert_array_equal(analogs[labels.index("Fx1")], 0.0)


def test_c3d_cop_is_masked_where_the_plate_is_unloaded(c3d_file, columns):
    labels = c3d_parameter(c3d_file, "ANALOG", "LABELS")
    analogs = c3d_file["data"]["analogs"][0, :, :SAMPLE_COUNT]
    unloaded = columns["plate_force_z_n"][:, 1] < COP_FORCE_THRESHOLD_N
    assert unloaded.sum() == LEFT_UNLOADED.stop - LEFT_UNLOADED.start
    px_left = analogs[labels.index("Px2")]
    assert np.all(np.isnan(px_left[unloaded]))
    np.testing.assert_allclose(px_left[~unloaded], columns["plate_cop_m"][~unloaded, 1, 0], atol=1e-7)
    assert not np.any(np.isnan(analogs[labels.index("Py1")]))
    points = c3d_parameter(c3d_file, "POINT", "LABELS")
    residuals = c3d_file["data"]["meta_points"]["residuals"][0]
    frame_unloaded = unloaded[::10]
    cop_left = points.index("COP_left")
    assert np.all(residuals[cop_left, frame_unloaded] < 0)
    assert np.all(residuals[cop_left, ~frame_unloaded] >= 0)
    assert np.all(np.isnan(c3d_file["data"]["points"][:3, cop_left, frame_unloaded]))


def test_c3d_force_platforms_sit_under_each_foot(c3d_file, columns):
    assert int(c3d_parameter(c3d_file, "FORCE_PLATFORM", "USED")[0]) == 2
    assert c3d_parameter(c3d_file, "FORCE_PLATFORM", "TYPE").tolist() == [1, 1]
    channel = c3d_parameter(c3d_file, "FORCE_PLATFORM", "CHANNEL")
    assert channel.shape == (6, 2)
    labels = c3d_parameter(c3d_file, "ANALOG", "LABELS")
    assert [labels[i - 1] for i in channel[:, 1]] == ["Fx2", "Fy2", "Fz2", "Px2", "Py2", "Mz2"]
    corners = c3d_parameter(c3d_file, "FORCE_PLATFORM", "CORNERS")
    assert corners.shape == (3, 4, 2)
    # Default twin (core/robot.py, since issue 13): feet side by side 0.4 m apart, platform 0.6 m high.
    np.testing.assert_allclose(corners.mean(axis=1).T, [[0.0, -0.2, 0.6], [0.0, 0.2, 0.6]], atol=1e-6)
    length_x, width_y = DEFAULT_FOOT_PLATE_SIZE_M
    np.testing.assert_allclose(corners[:, 0, 0] - corners[:, 2, 0], [length_x, width_y, 0.0], atol=1e-6)
    # ezc3d's own force-platform reader puts the COP where the plate frame says it is.
    right = c3d_file["data"]["platform"][0]
    expected_cop = np.array([columns["plate_cop_m"][:, 0, 0], -0.2 + columns["plate_cop_m"][:, 0, 1]])
    np.testing.assert_allclose(right["center_of_pressure"][:2, :SAMPLE_COUNT], expected_cop, atol=1e-6)
    np.testing.assert_allclose(right["force"][2, :SAMPLE_COUNT], columns["plate_force_z_n"][:, 0], rtol=1e-6)


def test_c3d_points_follow_the_moving_plates(c3d_file, columns):
    labels = c3d_parameter(c3d_file, "POINT", "LABELS")
    points = c3d_file["data"]["points"][:3]
    frames = np.arange(points.shape[2]) * 10
    plate_right = points[:, labels.index("PLATE_right")]
    cop_right = points[:, labels.index("COP_right")]
    # A rigid transform keeps the COP's distance from the plate centre.
    np.testing.assert_allclose(
        np.linalg.norm(cop_right - plate_right, axis=0),
        np.linalg.norm(columns["plate_cop_m"][frames, 0], axis=1),
        atol=1e-6,
    )
    # The stance frame sways 20 mm along y: both plates follow it.
    sway_y = columns["stance_pose"][frames, 1]
    assert np.ptp(plate_right[1]) == pytest.approx(np.ptp(sway_y), rel=0.2)


def test_c3d_events_have_labels_contexts_and_times(c3d_file):
    event = c3d_file["parameters"]["EVENT"]
    assert int(event["USED"]["value"][0]) == 2
    assert event["LABELS"]["value"] == ["pause", "fall"]
    assert event["CONTEXTS"]["value"] == ["General", "Left"]
    times = event["TIMES"]["value"]
    np.testing.assert_allclose(times[0] * 60.0 + times[1], [0.5, 2.5], atol=1e-6)
    assert "detector=harness_load" in event["DESCRIPTIONS"]["value"][1]
    subject = c3d_file["parameters"]["SUBJECTS"]["NAMES"]["value"][0]
    assert subject.startswith("P-") and event["SUBJECTS"]["value"] == [subject, subject]


def test_c3d_flags_a_missing_tick_instead_of_refusing_the_log(twin, columns, tmp_path: Path):
    """Issue 20 defect 11: a lost sample made the C3D export refuse the whole run."""
    gappy = {name: np.delete(values, 100, axis=0) for name, values in columns.items()}
    gappy_log = SessionLog(columns=gappy, events=[], metadata=metadata_for(twin))
    path = tmp_path / "gappy.c3d"
    path.write_bytes(export_session(gappy_log, "c3d")[0])
    c3d = ezc3d.c3d(str(path))
    gap = c3d["data"]["analogs"][0, c3d["parameters"]["ANALOG"]["LABELS"]["value"].index("tick_gap")]
    assert np.flatnonzero(gap[: len(gappy["tick"])]).tolist() == [100]


def test_c3d_refuses_an_unknown_stance_pose(twin, columns):
    unknown = dict(columns, stance_pose=columns["stance_pose"].copy())
    unknown["stance_pose"][42, 2] = np.nan
    with pytest.raises(SessionLogError) as refused:
        export_session(SessionLog(columns=unknown, metadata=metadata_for(twin)), "c3d")
    assert refused.value.field == "stance_pose[42]"


def test_c3d_frame_ratio_keeps_frames_within_the_c3d_limit():
    assert c3d_frame_ratio(1000.0, 3000) == 10
    assert c3d_frame_ratio(1000.0, 700_000) == 20  # 35 min would exceed 65535 frames at 100 Hz
    assert c3d_frame_ratio(100.0, 500) == 1
    assert c3d_frame_ratio(1000.0, 1_200_000) == 20
    assert c3d_frame_ratio(1000.0, 1_400_000) == 25
    with pytest.raises(SessionLogError):
        c3d_frame_ratio(1000.0, 65535 * 1000 + 1)


def test_an_unknown_field_gets_numbered_channels_with_the_unit_of_its_name(twin, columns):
    extra = dict(columns, belt_force_n=np.ones((SAMPLE_COUNT, 3)), segment=np.zeros(SAMPLE_COUNT, dtype=np.int16))
    units = SessionLog(columns=extra, metadata=metadata_for(twin)).channel_units()
    assert [units[f"belt_force_{i}"]["unit"] for i in (1, 2, 3)] == ["N", "N", "N"]
    assert units["segment"] == {"unit": "", "field": "segment"}
    assert units["cue_angular_velocity_z"]["unit"] == "rad/s" and units["tick_compute"]["unit"] == "us"


# --- Pseudonymisation ------------------------------------------------------------------------------


def test_pseudonymise_keeps_anthropometrics_and_replaces_identity():
    record = pseudonymise(PATIENT, SALT, session_date=dt.date(2024, 3, 1))
    kept = {"sex", "height_m", "body_mass_kg", "affected_side", "age_at_session_years"}
    assert set(record) == {"pseudonym_id", *kept}  # issue 16 §9: no free text (diagnosis, notes) by default
    assert record["age_at_session_years"] == 62  # born 15 July 1961, not yet 63 on 1 March 2024
    assert pseudonymise(PATIENT, SALT, session_date=dt.date(2024, 7, 15))["age_at_session_years"] == 63
    assert record["pseudonym_id"] == pseudonymise(dict(PATIENT, notes="other"), SALT)["pseudonym_id"]
    assert record["pseudonym_id"] != pseudonymise(PATIENT, SALT + "x")["pseudonym_id"]
    assert record["pseudonym_id"] != pseudonymise(dict(PATIENT, identifier="MRN-0042918"), SALT)["pseudonym_id"]


def test_pseudonymise_refuses_short_salt_and_unknown_fields():
    with pytest.raises(SessionLogError) as short:
        pseudonymise(PATIENT, "short")
    assert short.value.field == "salt" and "short" not in str(short.value)
    with pytest.raises(SessionLogError) as unknown:
        pseudonymise(dict(PATIENT, mothers_maiden_name="Smith"), SALT)
    assert unknown.value.field == "patient.mothers_maiden_name"
    with pytest.raises(SessionLogError) as missing:
        pseudonymise({k: v for k, v in PATIENT.items() if k != "identifier"}, SALT)
    assert missing.value.field == "patient.identifier"


@pytest.mark.parametrize("fmt", ["csv", "parquet", "json", "c3d"])
def test_no_export_contains_name_identifier_or_birth_date(log, fmt):
    data = export_session(log, fmt)[0]
    if fmt == "csv":
        archive = zipfile.ZipFile(io.BytesIO(data))
        contents = [archive.read(name) for name in archive.namelist()]
    else:
        contents = [data]
    for content in contents:
        for secret in ("Jane", "Example", "MRN-0042917", "1961-07-15", "daughter"):
            assert secret.encode() not in content, (fmt, secret)


# --- Validation ------------------------------------------------------------------------------------


@pytest.mark.parametrize("missing", REQUIRED_COLUMNS)
def test_log_without_a_required_column_is_refused_naming_it(twin, columns, missing):
    with pytest.raises(SessionLogError) as refused:
        SessionLog(columns={k: v for k, v in columns.items() if k != missing}, metadata=metadata_for(twin))
    assert refused.value.field == missing


def test_columns_of_unequal_length_are_refused_naming_the_column(twin, columns):
    with pytest.raises(SessionLogError) as refused:
        SessionLog(columns=dict(columns, harness_load_n=columns["harness_load_n"][:-1]), metadata=metadata_for(twin))
    assert refused.value.field == "harness_load_n"
    assert refused.value.value == SAMPLE_COUNT - 1


def test_misshapen_and_non_numeric_columns_are_refused(twin, columns):
    with pytest.raises(SessionLogError) as shape:
        SessionLog(columns=dict(columns, stance_pose=columns["stance_pose"][:, :5]), metadata=metadata_for(twin))
    assert shape.value.field == "stance_pose"
    objects = np.empty(SAMPLE_COUNT, dtype=object)
    with pytest.raises(SessionLogError) as kind:
        SessionLog(columns=dict(columns, harness_load_n=objects), metadata=metadata_for(twin))
    assert kind.value.field == "harness_load_n"


def test_clock_and_sample_rate_are_checked(twin, columns):
    backwards = columns["time_s"].copy()
    backwards[7] = backwards[6]
    with pytest.raises(SessionLogError) as clock:
        SessionLog(columns=dict(columns, time_s=backwards), metadata=metadata_for(twin))
    assert clock.value.field == "time_s[7]"
    with pytest.raises(SessionLogError) as rate:
        SessionLog(columns=columns, metadata=dict(metadata_for(twin), sample_rate_hz=0.0))
    assert rate.value.field == "metadata.sample_rate_hz"
    # The nominal rate is kept whatever the stamps say (issue 20 defect 11): late ticks are flags, not errors.
    assert SessionLog(columns=columns, metadata=dict(metadata_for(twin), sample_rate_hz=500.0)).sample_rate_hz == 500.0
    with pytest.raises(SessionLogError) as session:
        SessionLog(columns=columns, metadata={"sample_rate_hz": SAMPLE_RATE_HZ})
    assert session.value.field == "metadata.session_id"


def test_malformed_events_are_refused_naming_the_field(twin, columns):
    events = synthetic_events()
    del events[1]["kind"]
    with pytest.raises(SessionLogError) as missing_kind:
        SessionLog(columns=columns, events=events, metadata=metadata_for(twin))
    assert missing_kind.value.field == "events[1].kind"
    events = synthetic_events()
    events[0]["details"] = {"load_n": float("nan")}
    with pytest.raises(SessionLogError) as nan_details:
        SessionLog(columns=columns, events=events, metadata=metadata_for(twin))
    assert nan_details.value.field == "events[0].details"


def test_unknown_format_is_refused(log):
    with pytest.raises(SessionLogError) as refused:
        export_session(log, "xlsx")
    assert refused.value.field == "format"


def test_c3d_needs_the_robot_geometry(columns, log):
    without_robot = {k: v for k, v in log.metadata.items() if k != "robot"}
    with pytest.raises(SessionLogError) as refused:
        export_session(SessionLog(columns=columns, metadata=without_robot), "c3d")
    assert refused.value.field == "metadata.robot"


# --- Bundle ----------------------------------------------------------------------------------------


def test_bundle_has_a_folder_per_session_and_a_pseudonymised_index(twin, columns, tmp_path: Path):
    other_patient = dict(PATIENT, identifier="MRN-7", name="John Other", diagnosis="stroke", affected_side="right")
    logs = [
        SessionLog(columns=columns, events=synthetic_events(), metadata=metadata_for(twin, "41")),
        SessionLog(
            columns=columns,
            events=[],
            metadata=metadata_for(twin, "42", patient=other_patient, started_utc=STARTED_UTC + dt.timedelta(days=9)),
        ),
    ]
    selection = {"from": "2024-03-01", "to": "2024-03-31", "diagnosis": None}
    archive = zipfile.ZipFile(io.BytesIO(export_bundle(logs, selection=selection)))
    names = set(archive.namelist())
    for folder in ("session-41", "session-42"):
        for member in (
            "metadata.json",
            "telemetry.csv",
            "events.csv",
            "session.parquet",
            "session.json",
            "session.c3d",
        ):
            assert f"{folder}/{member}" in names
    index = list(csv.DictReader(io.StringIO(archive.read("index.csv").decode())))
    assert [row["diagnosis"] for row in index] == ["", ""]  # free text only when asked for
    assert [row["session_date"] for row in index] == ["2024-03-01", "2024-03-10"]
    assert index[0]["event_kinds"] == "fall:1;pause:1" and index[1]["event_count"] == "0"
    assert all(row["pseudonym_id"].startswith("P-") for row in index)
    assert index[0]["pseudonym_id"] != index[1]["pseudonym_id"]
    assert json.loads(archive.read("index.json"))["selection"] == selection
    for member in names:
        content = archive.read(member)
        for secret in ("Jane", "John", "MRN-0042917", "MRN-7"):
            assert secret.encode() not in content, (member, secret)
    # A file from inside the bundle opens in its standard reader.
    path = tmp_path / "inner.c3d"
    path.write_bytes(archive.read("session-42/session.c3d"))
    assert ezc3d.c3d(str(path))["parameters"]["SSP_REHAB"]["SESSION_ID"]["value"] == ["42"]
    assert pq.read_table(io.BytesIO(archive.read("session-41/session.parquet"))).num_rows == SAMPLE_COUNT


def test_bundle_refuses_identified_patients_and_duplicate_sessions(twin, columns):
    identified = SessionLog(columns=columns, metadata=metadata_for(twin, "43", identified=True))
    assert identified.metadata["patient"]["name"] == PATIENT["name"]
    with pytest.raises(SessionLogError) as refused:
        export_bundle([identified], formats=["json"])
    assert refused.value.field == "logs[0].metadata.patient.identifier"
    assert export_bundle([identified], formats=["json"], allow_identified=True)
    twice = SessionLog(columns=columns, metadata=metadata_for(twin, "44"))
    with pytest.raises(SessionLogError) as duplicate:
        export_bundle([twice, twice], formats=["json"])
    assert duplicate.value.field == "logs[1].metadata.session_id"


def test_session_metadata_records_geometry_and_software_version(twin):
    metadata = metadata_for(twin)
    assert metadata["robot"] == twin_to_dict(twin)
    assert metadata["patient_identified"] is False
    assert "name" not in metadata["patient"] and "date_of_birth" not in metadata["patient"]
    assert metadata["patient"]["age_at_session_years"] == 62


def test_worker_telemetry_records_export_with_named_channels_and_code_tables(twin, columns, tmp_path: Path):
    records = np.zeros(SAMPLE_COUNT, dtype=TELEMETRY_DTYPE)
    for name in set(columns) & set(TELEMETRY_DTYPE.names or ()):
        records[name] = columns[name]
    records["utc_s"] = STARTED_UTC.timestamp() + np.arange(SAMPLE_COUNT) / SAMPLE_RATE_HZ
    records["state"] = SupervisorState.RUNNING
    worker_log = SessionLog.from_telemetry(records, synthetic_events(), metadata_for(twin))
    table = pq.read_table(io.BytesIO(export_session(worker_log, "parquet")[0]))
    assert table.schema.field("measured_stance_pose_roll").metadata[b"unit"] == b"rad"
    assert table.schema.field("drive_state_left_6").metadata[b"field"] == b"drive_state"
    np.testing.assert_array_equal(table.column("utc").to_numpy(), records["utc_s"])
    sidecar = json.loads(table.schema.metadata[b"ssp_rehab.metadata"])
    assert sidecar["recording"]["codes"]["state"][str(int(SupervisorState.RUNNING))] == "running"
    path = tmp_path / "worker.c3d"
    path.write_bytes(export_session(worker_log, "c3d")[0])
    labels = ezc3d.c3d(str(path))["parameters"]["ANALOG"]["LABELS"]["value"]
    assert "slider_velocity_right_2" in labels and "utc" not in labels  # POSIX seconds exceed float32
    with pytest.raises(SessionLogError) as refused:
        SessionLog.from_telemetry(records["harness_load_n"], [], metadata_for(twin))
    assert refused.value.field == "telemetry"


def test_streamed_exports_hold_one_batch_not_the_run(twin, tmp_path: Path):
    """Issue 20 Build 7: an export's memory must not grow with the run. The same export of a run four times
    longer, read in batches from its spool, peaks at about the same Python allocations (tracemalloc; the hard
    figures, RSS included, are in `ssp-rehab bench exports`)."""
    import tracemalloc

    from server.exports.formats import write_csv, write_json, write_parquet
    from server.exports.stream import ForwardSink, LogStream, RecordSpool
    from server.realtime.telemetry import TELEMETRY_DTYPE

    class Discard(io.RawIOBase):
        def writable(self) -> bool:
            return True

        def write(self, data) -> int:
            return len(memoryview(data))

    def peak_bytes(sample_count: int) -> int:
        spool = RecordSpool(tmp_path / f"{sample_count}.records")
        for start in range(0, sample_count, 500):
            records = np.zeros(500, dtype=TELEMETRY_DTYPE)
            records["tick"] = np.arange(start, start + 500)
            records["time_s"] = records["tick"] / SAMPLE_RATE_HZ
            spool.append(records)
        log = LogStream(spool.mapped(), synthetic_events(), metadata_for(twin), batch_samples=500)
        tracemalloc.start()
        try:
            for writer in (write_csv, write_parquet, write_json):
                writer(log, ForwardSink(Discard()))
            return tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
            spool.remove()

    short, long = peak_bytes(2_000), peak_bytes(8_000)
    assert long < 1.5 * short, (short, long)


def test_the_posturography_command_measures_an_exported_c3d_as_the_run_was_recorded(log, columns, twin, tmp_path):
    """Issue 22 §5: a C3D the product exported gives the COP measures of the run's own net COP (the two plates
    weighted by their vertical force; a plate under 20 N carries no COP)."""
    from core.posturography import net_cop, sway_metrics
    from server.cli.posturography_commands import measures
    from server.sessions.balance import foot_origins_m

    data, _, filename = export_session(log, "c3d")
    path = tmp_path / filename
    path.write_bytes(data)
    measured = measures(path, filtered=False)

    force = columns["plate_force_z_n"]
    loaded = np.where(force >= COP_FORCE_THRESHOLD_N, force, 0.0)
    cop = net_cop(loaded, columns["plate_cop_m"], foot_origins_m(twin))
    expected = sway_metrics(np.arange(SAMPLE_COUNT) / SAMPLE_RATE_HZ, cop)
    assert measured["window"]["samples"] == SAMPLE_COUNT  # the padded last frame is not a sample
    assert measured["measures"]["mean_velocity_mm_s"] == pytest.approx(expected.mean_velocity_m_s * 1e3, rel=1e-5)
    assert measured["measures"]["confidence_ellipse_area_95_mm2"] == pytest.approx(
        expected.confidence_ellipse_area_95_m2 * 1e6, rel=1e-5
    )
    assert measured["measures"]["range_ap_mm"] == pytest.approx(expected.range_ap_m * 1e3, rel=1e-5)
