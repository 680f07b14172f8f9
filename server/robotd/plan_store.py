"""Plans ahead, stored (issue 21, build 1): each checked plan once, under the data directory, by the hash
of everything it is a function of.

    key = hash(prescription content, the patient parameters that enter it, the robot description, the
              plan and supervisor settings, the control rate, the planning code)

A plan is a directory `<data>/plans/<key>/`: the arrays the worker plays (`poses.npy`, `cue.npy`,
`segment.npy`, `segment_start.npy`), the rest of the plan (`plan.pickle`) and its check report
(`report.json`), or only `refused.json` when the check refused it. It is written under a temporary name
and renamed, so a plan is there whole or not at all, and owner-only like the rest of the data directory.

Readers map the arrays: the robot daemon and its worker share the file's pages instead of copying them
through a pipe (a `StoredMotion` pickles as its directory), and the worker gives back the pages it has
played (`release_before`), so a 60-minute plan does not stay resident.
"""

from __future__ import annotations

import functools
import hashlib
import json
import mmap
import os
import pickle
import shutil
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from core.plan.build import PrescriptionPlan
from core.plan.motion import PlannedMotion
from server.file_modes import private_directory

PLAN_FORMAT = 1
ARRAYS = ("poses", "cue", "segment", "segment_start")
CORE_DIRECTORY = Path(__file__).resolve().parents[2] / "core"


@functools.cache
def code_version() -> str:
    """A hash of the planning code (every module under core/): a plan made by other code is made again."""
    digest = hashlib.sha256()
    for path in sorted(CORE_DIRECTORY.rglob("*.py")):
        digest.update(path.relative_to(CORE_DIRECTORY).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:16]


def plan_key(
    content: Mapping[str, Any],
    patient: Mapping[str, Any] | None,
    *,
    robot_digest: str,
    config: Mapping[str, Any],
    control_rate_hz: int,
) -> str:
    """The plan's identity: equal keys, equal plans."""
    canonical = json.dumps(
        {
            "format": PLAN_FORMAT,
            "code": code_version(),
            "prescription": content,
            "patient": patient,
            "robot": robot_digest,
            "config": config,
            "control_rate_hz": control_rate_hz,
        },
        sort_keys=True,
        separators=(",", ":"),
        allow_nan=False,
    )
    return hashlib.sha256(canonical.encode()).hexdigest()[:24]


class _MappedArray:
    """A .npy file mapped read-only; `release_before` returns played pages to the kernel."""

    def __init__(self, path: Path) -> None:
        with path.open("rb") as handle:
            npy = np.lib.format
            version = npy.read_magic(handle)
            read_header = npy.read_array_header_1_0 if version == (1, 0) else npy.read_array_header_2_0
            shape, fortran, dtype = read_header(handle)
            self.offset = handle.tell()
            self.map = mmap.mmap(handle.fileno(), 0, access=mmap.ACCESS_READ)
        assert not fortran
        count = int(np.prod(shape))
        self.array = np.frombuffer(self.map, dtype=dtype, count=count, offset=self.offset).reshape(shape)
        self.row_bytes = self.array.itemsize * (int(np.prod(shape[1:])) if len(shape) > 1 else 1)

    def release_before(self, row: int) -> None:
        end = (self.offset + row * self.row_bytes) // mmap.PAGESIZE * mmap.PAGESIZE
        if end > 0:
            self.map.madvise(mmap.MADV_DONTNEED, 0, end)


def _load_motion(directory: str) -> StoredMotion:
    mapped = {name: _MappedArray(Path(directory) / f"{name}.npy") for name in ARRAYS}
    arrays = {name: mapped[name].array for name in ARRAYS}
    return StoredMotion(**arrays, directory=directory, mapped=mapped)


@dataclass(frozen=True)
class StoredMotion(PlannedMotion):
    """A plan's motion mapped from the store."""

    directory: str = ""
    mapped: Mapping[str, _MappedArray] | None = None

    def __reduce__(self) -> tuple[Any, tuple[str]]:
        return _load_motion, (self.directory,)  # the receiver maps the same file: nothing is copied

    def release_before(self, index: int) -> None:
        """The samples before `index` are played: their pages may go (they are read back if needed)."""
        if self.mapped is not None:
            for name in ("poses", "cue", "segment"):
                self.mapped[name].release_before(index)


class PlanStore:
    def __init__(self, directory: Path, max_bytes: int | None = None) -> None:
        self.directory = directory
        self.max_bytes = max_bytes  # None: unbounded (tools); the daemon bounds it (settings.plan_store_max_mb)

    def path(self, key: str) -> Path:
        return self.directory / key

    def has(self, key: str) -> bool:
        return (self.path(key) / "report.json").exists()

    def refusal(self, key: str) -> dict[str, Any] | None:
        """Why the check refused this plan, if it did."""
        path = self.path(key) / "refused.json"
        return json.loads(path.read_text()) if path.exists() else None

    def save(self, key: str, plan: PrescriptionPlan, report: dict[str, Any]) -> None:
        motion = plan.played

        def write(directory: Path) -> None:
            for name in ARRAYS:
                np.save(directory / f"{name}.npy", getattr(motion, name), allow_pickle=False)
            (directory / "plan.pickle").write_bytes(pickle.dumps(replace(plan, motion=None)))
            (directory / "report.json").write_text(json.dumps(report))

        self._write(key, write)

    def save_refusal(self, key: str, refusal: dict[str, Any]) -> None:
        self._write(key, lambda directory: (directory / "refused.json").write_text(json.dumps(refusal)))

    def load(self, key: str) -> tuple[PrescriptionPlan, dict[str, Any]]:
        """The stored plan with its motion mapped, and its check report (marked as used)."""
        directory = self.path(key)
        os.utime(directory)
        plan: PrescriptionPlan = pickle.loads((directory / "plan.pickle").read_bytes())  # our own file, owner-only
        report = json.loads((directory / "report.json").read_text())
        return replace(plan, motion=_load_motion(str(directory))), report

    def _write(self, key: str, write: Any) -> None:
        private_directory(self.directory)
        final = self.path(key)
        staging = self.directory / f".{key}.{os.getpid()}"
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir(mode=0o700)
        write(staging)
        if final.exists():  # made meanwhile by another process: equal keys, equal plans
            shutil.rmtree(staging, ignore_errors=True)
            return
        os.replace(staging, final)
        self.prune(keep=key)

    def prune(self, keep: str | None = None) -> list[str]:
        """Remove the least recently used plans until the store fits `max_bytes` (never `keep`); returns
        their keys. A removed plan is made again when a booking needs it. Open maps of it stay valid."""
        if self.max_bytes is None or not self.directory.exists():
            return []
        plans = [path for path in self.directory.iterdir() if path.is_dir() and not path.name.startswith(".")]
        sizes = {path: sum(item.stat().st_size for item in path.iterdir()) for path in plans}
        total, removed = sum(sizes.values()), []
        for path in sorted(plans, key=lambda item: item.stat().st_mtime):
            if total <= self.max_bytes:
                break
            if path.name == keep:
                continue
            shutil.rmtree(path, ignore_errors=True)
            total -= sizes[path]
            removed.append(path.name)
        return removed
