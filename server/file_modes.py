"""The data directory holds password hashes, patient data, the token key and the run journals: what this
service creates there is readable by its owner only, and what it finds open to others at start-up is
tightened, with a warning that says so (issue 20, defect 19: the SQLite file was created 0644)."""

from __future__ import annotations

import logging
import os
import stat
from pathlib import Path

OWNER_ONLY_FILE = 0o600
OWNER_ONLY_DIRECTORY = 0o700
logger = logging.getLogger(__name__)


def private_directory(path: Path) -> Path:
    """`path` and the parents this call creates, owner-only; an existing `path` is tightened."""
    missing = []
    for directory in (path, *path.parents):
        if directory.exists():
            break
        missing.append(directory)
    for directory in reversed(missing):
        directory.mkdir(mode=OWNER_ONLY_DIRECTORY, exist_ok=True)
    tighten(path, OWNER_ONLY_DIRECTORY)
    return path


def private_file(path: Path) -> Path:
    """`path` created empty and owner-only if it does not exist, else tightened."""
    try:
        os.close(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, OWNER_ONLY_FILE))
    except FileExistsError:
        tighten(path, OWNER_ONLY_FILE)
    return path


def tighten(path: Path, allowed: int) -> None:
    """Take from `path` every permission bit outside `allowed` (never adds one), and say so."""
    try:
        current = stat.S_IMODE(path.stat().st_mode)
    except FileNotFoundError:
        return
    permissions = current & 0o777
    if permissions & ~allowed:
        try:
            os.chmod(path, (current & ~0o777) | (permissions & allowed))
        except PermissionError:
            logger.warning("%s is open to others (%s) and not ours to tighten: restrict it", path, oct(permissions))
            return
        logger.warning("%s was open to others (%s): tightened to %s", path, oct(permissions), oct(allowed & current))
