"""The session log's JSON metadata sidecar, with the patient pseudonymised by default (issue 6 §5).

Pseudonymisation keeps what a fall-detection study needs (sex, height, body mass, age at the session,
affected side) and replaces the name, identifier and date of birth by a stable id: an
HMAC-SHA256 of the identifier keyed with a secret salt, so the same patient gets the same id in every
export made with that salt, and the id cannot be reversed by hashing candidate hospital numbers
without the salt. Free-text fields (diagnosis, notes, contraindications) may name people, places or rare
conditions, so they are left out unless the export asks for them. Patient fields are an allow-list: a field
this module does not know is refused rather than copied, so that a new free-text column can never leak into
a study export.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
from collections.abc import Mapping
from importlib import metadata as package_metadata
from typing import Any

from core.robot import TwinRobot, twin_to_dict
from server.exports.log import SessionLogError

PACKAGE_NAME = "ssp-rehab"
KEPT_PATIENT_FIELDS = ("sex", "height_m", "body_mass_kg", "affected_side", "age_at_session_years")
# Free text may name people or places: only in an export that asks for it (`include_free_text`).
FREE_TEXT_PATIENT_FIELDS = ("diagnosis", "notes", "contraindications")
IDENTIFYING_PATIENT_FIELDS = (
    "identifier",
    "name",
    "first_name",
    "last_name",
    "date_of_birth",
    *FREE_TEXT_PATIENT_FIELDS,
    "id",  # database keys re-identify anyone with database access
    "patient_id",
    "created_at",
    "updated_at",
)
SALT_MIN_LENGTH = 16
PSEUDONYM_HEX_DIGITS = 16  # 64 bits: collisions negligible for any clinic's patient count


def software_version() -> str:
    """The installed ssp-rehab version, from the package metadata."""
    try:
        return package_metadata.version(PACKAGE_NAME)
    except package_metadata.PackageNotFoundError:
        return "unknown (not installed)"


def pseudonym_id(identifier: str, salt: str | bytes) -> str:
    """Stable salted id of a patient identifier: `P-` and 16 hex digits of HMAC-SHA256(salt, identifier)."""
    salt_bytes = salt.encode() if isinstance(salt, str) else bytes(salt)
    if len(salt_bytes) < SALT_MIN_LENGTH:
        # The salt is a secret: report its length, never its value.
        raise SessionLogError("salt", f"<{len(salt_bytes)} bytes>", f"at least {SALT_MIN_LENGTH} bytes")
    digest = hmac.new(salt_bytes, identifier.encode(), hashlib.sha256).hexdigest()
    return f"P-{digest[:PSEUDONYM_HEX_DIGITS]}"


def _as_date(field_name: str, value: object) -> dt.date:
    if isinstance(value, dt.datetime):
        return value.date()
    if isinstance(value, dt.date):
        return value
    if isinstance(value, str):
        try:
            return dt.datetime.fromisoformat(value).date()
        except ValueError:
            pass
    raise SessionLogError(field_name, value, "an ISO 8601 date or a date")


def age_in_years(date_of_birth: object, on_date: object) -> int:
    """Whole years of age on `on_date` (whole years only: a finer age would narrow down the birth date)."""
    born = _as_date("patient.date_of_birth", date_of_birth)
    today = _as_date("session_date", on_date)
    if born > today:
        raise SessionLogError("patient.date_of_birth", born.isoformat(), f"must not be after {today.isoformat()}")
    return today.year - born.year - ((today.month, today.day) < (born.month, born.day))


def _identifier(patient: Mapping[str, Any]) -> str:
    identifier = patient.get("identifier")
    if not isinstance(identifier, str) or not identifier.strip():
        raise SessionLogError("patient.identifier", identifier, "a non-empty string (the pseudonym is derived from it)")
    return identifier


def pseudonymise(
    patient: Mapping[str, Any], salt: str | bytes, *, session_date: object = None, include_free_text: bool = False
) -> dict[str, Any]:
    """The patient's anthropometrics with name, identifier and date of birth replaced by `pseudonym_id`.

    `age_at_session_years` is computed from the date of birth when `session_date` is given. The free-text
    fields (diagnosis, notes, contraindications) are left out unless `include_free_text`.
    """
    known = set(KEPT_PATIENT_FIELDS) | set(IDENTIFYING_PATIENT_FIELDS)
    for key in patient:
        if key not in known:
            raise SessionLogError(f"patient.{key}", "<not shown>", "unknown patient field: neither kept nor removed")
    result: dict[str, Any] = {"pseudonym_id": pseudonym_id(_identifier(patient), salt)}
    result.update({key: patient[key] for key in KEPT_PATIENT_FIELDS if key in patient})
    if include_free_text:
        result.update({key: patient[key] for key in FREE_TEXT_PATIENT_FIELDS if key in patient})
    if session_date is not None and patient.get("date_of_birth") is not None:
        result["age_at_session_years"] = age_in_years(patient["date_of_birth"], session_date)
    return result


def identifying_fields(patient: Mapping[str, Any]) -> list[str]:
    """The identifying fields present in a patient record (empty for a pseudonymised one); free text asked
    for in a pseudonymised export does not count."""
    identifying = [key for key in IDENTIFYING_PATIENT_FIELDS if key not in FREE_TEXT_PATIENT_FIELDS]
    return [key for key in identifying if patient.get(key) not in (None, "")]


def session_metadata(
    *,
    session_id: str | int,
    started_utc: dt.datetime,
    sample_rate_hz: float,
    patient: Mapping[str, Any],
    prescription: Mapping[str, Any],
    prescription_version: int,
    twin: TwinRobot,
    salt: str | bytes,
    identified: bool = False,
    include_free_text: bool = False,
) -> dict[str, Any]:
    """The metadata of one session run: patient (pseudonymised unless `identified`), prescription
    version and segments, washout parameters per segment, robot geometry, software version, sample rate."""
    segments = prescription.get("segments")
    if not isinstance(segments, list) or not segments:
        raise SessionLogError("prescription.segments", segments, "a non-empty list of segments")
    if identified:
        patient_record = {"pseudonym_id": pseudonym_id(_identifier(patient), salt), **patient}
        if patient.get("date_of_birth") is not None:
            patient_record["age_at_session_years"] = age_in_years(patient["date_of_birth"], started_utc)
    else:
        patient_record = pseudonymise(patient, salt, session_date=started_utc, include_free_text=include_free_text)
    return {
        "session_id": str(session_id),
        "started_utc": started_utc.isoformat(),
        "sample_rate_hz": float(sample_rate_hz),
        "patient": patient_record,
        "patient_identified": identified,
        "prescription": {"version": prescription_version, "segments": segments},
        "washout_parameters": [segment.get("washout") for segment in segments],
        "robot": twin_to_dict(twin),
        "software": {"name": PACKAGE_NAME, "version": software_version()},
    }
