"""The command line answers at once (issue 21 §7): `--help` and `ik` import no service, plotting or
control-design library, and the help texts that spell a default keep it equal to the code's.

What it costs in seconds is measured by `ssp-rehab bench cli`, not here."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SERVICE_AND_PLOTTING = ("fastapi", "sqlalchemy", "matplotlib", "control", "uvicorn", "pymoo", "osqp", "mujoco")


def imported_by(*arguments: str) -> set[str]:
    """Top-level packages in sys.modules after `ssp-rehab ARGUMENTS` ran in a fresh interpreter."""
    script = (
        "import json, runpy, sys\n"
        f"sys.argv = ['ssp-rehab', *{list(arguments)!r}]\n"
        "try:\n    runpy.run_module('server.cli.main', run_name='__main__')\n"
        "except SystemExit:\n    pass\n"
        "print(json.dumps(sorted({name.split('.')[0] for name in sys.modules})), file=sys.stderr)\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        check=False,
        timeout=600,
    )
    return set(json.loads(done.stderr.strip().splitlines()[-1]))


def test_help_imports_no_numerics_and_no_service() -> None:
    found = imported_by("--help") & {"numpy", "numba", "scipy", *SERVICE_AND_PLOTTING}
    assert found == set()


@pytest.mark.parametrize("command", [["bench", "--help"], ["cueing", "--help"], ["realtime", "--help"]])
def test_a_command_group_help_imports_no_numerics(command: list[str]) -> None:
    assert imported_by(*command) & {"numpy", "numba", "scipy", *SERVICE_AND_PLOTTING} == set()


def test_ik_imports_the_kinematics_only() -> None:
    assert imported_by("ik", "--pose", "0", "0", "600", "0", "0", "0") & set(SERVICE_AND_PLOTTING) == set()


def option_help(path: list[str], option: str) -> str:
    import typer

    from server.cli.main import app

    command = typer.main.get_command(app)
    for name in path:
        command = command.commands[name]  # type: ignore[attr-defined]
    return next(p.help for p in command.params if option in p.opts)


def test_help_texts_spell_the_code_defaults() -> None:
    from core import tuning
    from core.plan.config import DEFAULT_CONTROL_RATE_HZ
    from core.robot import NAMED_LAYOUTS
    from server.cli.robot_option import BUILT_IN_LAYOUTS

    assert tuple(sorted(NAMED_LAYOUTS)) == BUILT_IN_LAYOUTS
    for command in (["realtime", "check"], ["realtime", "run"]):
        assert f"default {DEFAULT_CONTROL_RATE_HZ} Hz" in option_help(command, "--rate")
    assert f"default {tuning.TILT_COORDINATION_OFF_FRACTION}" in option_help(["tune"], "--tilt-coordination-min")
