"""The `--robot FILE` option shared by commands that use the robot description."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import typer

if TYPE_CHECKING:
    from core.robot import TwinRobot

# The names of core.robot.NAMED_LAYOUTS, spelled here so that `--help` need not import the robot model (and
# numba); tests/server/test_cli_startup.py keeps the two equal.
BUILT_IN_LAYOUTS = ("legacy-interleaved", "side-by-side")

ROBOT_OPTION = typer.Option(
    None,
    "--robot",
    help="Robot description TOML, or a built-in layout: " + ", ".join(BUILT_IN_LAYOUTS) + " (default: side-by-side).",
)


def twin_from_option(path: Path | None) -> TwinRobot:
    """The twin described by `path` (a TOML file or a built-in layout's name), or the default; invalid
    files raise core.robot.DescriptionError (an InvalidValueError)."""
    from core.robot import NAMED_LAYOUTS, default_twin, load_twin, named_twin

    if path is None:
        return default_twin()
    if str(path) in NAMED_LAYOUTS and not path.exists():
        return named_twin(str(path))
    return load_twin(path)


__all__ = ["BUILT_IN_LAYOUTS", "ROBOT_OPTION", "twin_from_option"]
