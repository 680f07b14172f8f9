"""`ssp-rehab`: the command line. Each topic registers its commands from its own module."""

from __future__ import annotations

import typer

# Plain imports of the command modules, which import their science inside each command: `--help` answers
# at once, and a module that cannot be imported (a broken real-time stack, say) fails the command that needs
# it with its traceback, never leaving a command quietly missing (tests/server/test_plain_imports.py).
from server.cli import (
    bench_commands,
    cueing_commands,
    drives_commands,
    dynamics_commands,
    falls_commands,
    kinematics_commands,
    layout_commands,
    posturography_commands,
    realtime_commands,
    service_commands,
    washout_commands,
    workspace_commands,
)

app = typer.Typer(
    name="ssp-rehab",
    help="Twin 6-SSP balance-rehabilitation robot: kinematics, washout, dynamics, console service.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# Each module exposes `register(app: typer.Typer) -> None`; this order is the order of `--help`.
COMMAND_MODULES = (
    kinematics_commands,
    workspace_commands,
    layout_commands,
    bench_commands,
    realtime_commands,
    dynamics_commands,
    drives_commands,
    service_commands,
    falls_commands,
    posturography_commands,
    washout_commands,
    cueing_commands,
)

for _module in COMMAND_MODULES:
    _module.register(app)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
