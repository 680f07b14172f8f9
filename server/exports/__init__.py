"""Session-log exports for fall-detection evaluation (issue 6 §5): CSV, Parquet, JSON, C3D, study bundles.

See docs/exports.md for the file layouts and conventions.
"""

from server.exports.bundle import export_bundle
from server.exports.formats import EXPORT_FORMATS, export_session, session_log_from_json
from server.exports.log import SessionLog, SessionLogError
from server.exports.metadata import pseudonymise, session_metadata

__all__ = [
    "EXPORT_FORMATS",
    "SessionLog",
    "SessionLogError",
    "export_bundle",
    "export_session",
    "pseudonymise",
    "session_log_from_json",
    "session_metadata",
]
