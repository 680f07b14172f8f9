"""The `--robot FILE` option shared by commands that use the robot description."""

from __future__ import annotations

from pathlib import Path

import typer

from core.robot import DescriptionError, TwinRobot, default_twin, load_twin

ROBOT_OPTION = typer.Option(None, "--robot", help="Robot description TOML (default: the paper's robot).")


def twin_from_option(path: Path | None) -> TwinRobot:
    """The twin described by `path`, or the built-in default; invalid files raise DescriptionError."""
    return default_twin() if path is None else load_twin(path)


__all__ = ["ROBOT_OPTION", "DescriptionError", "twin_from_option"]
