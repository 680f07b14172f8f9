"""What every command shares: JSON or human output, refusals, progress bars and saved plots."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import typer
from rich.console import Console

console = Console()
error_console = Console(stderr=True)


def emit(data: dict[str, Any], *, as_json: bool, human: Callable[[dict[str, Any]], None]) -> None:
    """Print `data` as JSON for scripts, or through `human` for people."""
    if as_json:
        from server.jsonable import to_jsonable  # numpy: only once there is something to print

        typer.echo(json.dumps(to_jsonable(data), indent=2))
    else:
        human(data)


def fail(message: str, *, as_json: bool = False, code: int = 2) -> typer.Exit:
    """Refuse with a message naming what was wrong; returns the Exit for `raise fail(...)`."""
    if as_json:
        typer.echo(json.dumps({"error": message}))
    else:
        error_console.print(f"[bold red]error:[/] {message}")
    return typer.Exit(code)


@contextmanager
def progress_bar(description: str, total: int, *, enabled: bool = True) -> Iterator[Callable[[int], None]]:
    """A rich progress bar on stderr (so `--json` stdout stays clean); yields `advance(n)`."""
    if not enabled:

        def ignore(_steps: int = 1) -> None:
            return None

        yield ignore
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
    )
    with Progress(*columns, console=error_console, transient=True) as progress:
        task = progress.add_task(description, total=total)

        def advance(steps: int = 1) -> None:
            progress.advance(task, steps)

        yield advance


def save_figure(figure: Any, directory: Path, name: str) -> Path:
    """Save a matplotlib figure as PNG in `directory` and close it."""
    import matplotlib.pyplot as plt

    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{name}.png"
    figure.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(figure)
    return path


def pyplot() -> Any:
    """matplotlib.pyplot on the headless Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def print_violations_by_reason(by_side: dict[str, dict[str, Any]]) -> None:
    """Every limit each robot breaks (`core.kinematics.violation_stretches`): samples and stretches of time."""
    for side, by_reason in by_side.items():
        for reason, found in by_reason.items():
            spans = ", ".join(f"{x['from_s']:.3f}–{x['to_s']:.3f} s" for x in found["stretches"])
            console.print(f"  {side} robot: {reason}: {found['samples']} samples ({spans})")
