"""`ssp-rehab`: the command line. Each topic registers its commands from its own module."""

from __future__ import annotations

import importlib

import typer

app = typer.Typer(
    name="ssp-rehab",
    help="Twin 6-SSP balance-rehabilitation robot: kinematics, washout, dynamics, console service.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# Each module exposes `register(app: typer.Typer) -> None`.
COMMAND_MODULES = (
    "server.cli.kinematics_commands",
    "server.cli.workspace_commands",
    "server.cli.layout_commands",
    "server.cli.bench_commands",
    "server.cli.realtime_commands",
    "server.cli.dynamics_commands",
    "server.cli.drives_commands",
    "server.cli.service_commands",
    "server.cli.falls_commands",
    "server.cli.washout_commands",
    "server.cli.cueing_commands",
)

for _module_name in COMMAND_MODULES:
    importlib.import_module(_module_name).register(app)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
