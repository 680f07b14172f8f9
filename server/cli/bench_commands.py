"""`ssp-rehab bench NAME`: run a benchmark from benchmarks/ and print (and optionally record) its figures."""

from __future__ import annotations

import importlib
import pkgutil
from typing import TYPE_CHECKING, Any

import typer

if TYPE_CHECKING:
    pass

from server.cli.output import console, emit, fail


def available() -> list[str]:
    import benchmarks

    return sorted(
        m.name.removeprefix("bench_") for m in pkgutil.iter_modules(benchmarks.__path__) if m.name.startswith("bench_")
    )


def _print_figures(data: dict[str, Any], indent: str = "") -> None:
    for key, value in data.items():
        if isinstance(value, dict):
            console.print(f"{indent}[bold]{key}[/]")
            _print_figures(value, indent + "  ")
        else:
            console.print(f"{indent}{key}: {value}")


def register(app: typer.Typer) -> None:
    @app.command()
    def bench(
        name: str = typer.Argument(..., help="Benchmark to run: " + ", ".join(available())),
        as_json: bool = typer.Option(False, "--json", help="Print figures as JSON."),
        quick: bool = typer.Option(False, "--quick", help="Smaller sizes: a smoke run, not for RESULTS.md."),
        write_results: bool = typer.Option(False, "--write-results", help="Record the dated figures in RESULTS.md."),
    ) -> None:
        """Run a speed/latency benchmark; figures include the target and whether it was met."""
        from benchmarks.results import record

        if name not in available():
            raise fail(f"bench name = {name!r}: must be one of {available()}", as_json=as_json)
        figures = importlib.import_module(f"benchmarks.bench_{name}").run(quick=quick)
        if write_results and not quick:
            record(name, figures)
        emit(figures, as_json=as_json, human=_print_figures)
