"""Preview jobs on disk (issue 21, defect 6): one owner-only JSON file per job under the data directory.

The console may run several web processes (`serve --workers 2`), and the poll of a job may reach another one
than the one that started it, so a job's state lives in a file every web process can read, never in memory.
The preview process writes it as it plans (`state` planning → ready | refused, `progress` 0–1), each time
whole to a temporary file that replaces the job's file (`os.replace`), so that a reader never sees half of it.
A job is read by the user who asked for it only (as export jobs, `server.exports.jobs`), and removed
`keep_s` after it finished.
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from server.file_modes import OWNER_ONLY_FILE, private_directory
from server.robotd.estop import process_alive

PREVIEW_JOBS_DIRECTORY = "preview-jobs"
# What the API shows of a job; the rest (the owner, the web process that runs it) is the store's own.
PUBLIC_FIELDS = ("preview_id", "state", "progress", "preview", "refusal", "error")
FINISHED_STATES = frozenset({"ready", "refused", "failed"})


@dataclass(frozen=True)
class PreviewJobStore:
    """The preview jobs under `directory`; picklable, so that the preview process writes through it too."""

    directory: Path
    keep_s: float

    def create(self, owner_id: int) -> dict[str, Any]:
        """A new job in state planning, owned by `owner_id` and run by this web process."""
        private_directory(self.directory)  # jobs hold patient data: owner-only, as the database file
        self.remove_expired()
        job = {"preview_id": uuid.uuid4().hex, "owner_id": owner_id, "web_pid": os.getpid(), "state": "planning",
               "progress": 0.0, "preview": None, "refusal": None, "error": None}  # fmt: skip
        self.write(job)
        return job

    def write(self, job: dict[str, Any]) -> None:
        """The job's file replaced by `job` at once (strict JSON; owner-only)."""
        path = self._path(job["preview_id"])
        temporary = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
        data = json.dumps(job, allow_nan=False, separators=(",", ":")).encode()
        descriptor = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, OWNER_ONLY_FILE)
        try:
            with os.fdopen(descriptor, "wb") as file:
                file.write(data)
            os.replace(temporary, path)
        except BaseException:
            temporary.unlink(missing_ok=True)
            raise

    def read(self, preview_id: str, owner_id: int) -> dict[str, Any] | None:
        """The job as the API shows it, for the user who asked for it only (None for anyone else)."""
        job = self._load(self._path(preview_id))
        if job is None or job.get("owner_id") != owner_id:
            return None
        if self._orphaned(job):
            job.update(state="failed", error="the console process that computed this preview stopped: ask again")
        return {key: job.get(key) for key in PUBLIC_FIELDS}

    def remove_expired(self) -> None:
        """Remove the jobs finished (or orphaned) more than `keep_s` ago, and temporary files left behind."""
        now = time.time()
        for path in self.directory.glob("*.json*"):
            with contextlib.suppress(FileNotFoundError):
                if now - path.stat().st_mtime <= self.keep_s:
                    continue
                job = None if path.name.startswith(".") else self._load(path)
                if job is None or job.get("state") in FINISHED_STATES or self._orphaned(job):
                    path.unlink()

    def _path(self, preview_id: str) -> Path:
        if len(preview_id) != 32 or not all(c in "0123456789abcdef" for c in preview_id):
            raise ValueError(f"not a preview job id: {preview_id!r}")  # never a path outside the directory
        return self.directory / f"{preview_id}.json"

    @staticmethod
    def _load(path: Path) -> dict[str, Any] | None:
        try:
            job = json.loads(path.read_bytes())
        except (FileNotFoundError, ValueError):
            return None
        return job if isinstance(job, dict) else None

    @staticmethod
    def _orphaned(job: dict[str, Any]) -> bool:
        """Still planning, but the web process whose preview process ran it is gone: it will never finish."""
        return job.get("state") == "planning" and not process_alive(int(job.get("web_pid", 0)))
