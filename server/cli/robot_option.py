"""The `--robot FILE` option shared by commands that use the robot description."""

from __future__ import annotations

from pathlib import Path

import typer

from core.robot import NAMED_LAYOUTS, DescriptionError, TwinRobot, default_twin, load_twin, named_twin

ROBOT_OPTION = typer.Option(
    None,
    "--robot",
    help="Robot description TOML, or a built-in layout: "
    + ", ".join(sorted(NAMED_LAYOUTS))
    + " (default: side-by-side).",
)


def twin_from_option(path: Path | None) -> TwinRobot:
    """The twin described by `path` (a TOML file or a built-in layout's name), or the default; invalid
    files raise DescriptionError."""
    if path is None:
        return default_twin()
    if str(path) in NAMED_LAYOUTS and not path.exists():
        return named_twin(str(path))
    return load_twin(path)


__all__ = ["ROBOT_OPTION", "DescriptionError", "twin_from_option"]
