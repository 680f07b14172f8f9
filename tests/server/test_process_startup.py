"""The robot's processes start without the plotting and control-design libraries (issue 21 §9).

python-control loads matplotlib and scipy.signal: 1.3 s of CPU in every process that imported it, measured,
and a console start runs five of them (the web process, the daemon, its stop listener, worker and planning
process). They load it only when they design a filter or a perception model."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PLOTTING_AND_CONTROL_DESIGN = {"matplotlib", "control"}


def printed_by(script: str) -> str:
    """What `script` prints in a fresh interpreter."""
    done = subprocess.run(
        [sys.executable, "-c", script],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        check=True,
        timeout=600,
    )
    return done.stdout.strip().splitlines()[-1]


def imported_by_import(module: str) -> set[str]:
    """Top-level packages in sys.modules after `import module` in a fresh interpreter."""
    listing = "print(json.dumps(sorted({name.split('.')[0] for name in sys.modules})))"
    return set(json.loads(printed_by(f"import json, sys\nimport {module}\n{listing}\n")))


@pytest.mark.parametrize(
    "module",
    ["server.robotd.estop_listener", "server.realtime.worker", "server.robotd.planner", "server.robotd.process"],
)
def test_a_robot_process_starts_without_plotting_or_control_design(module: str) -> None:
    assert imported_by_import(module) & PLOTTING_AND_CONTROL_DESIGN == set()


def test_the_stop_listener_starts_without_scipy_signal() -> None:
    """It only latches and confirms; a refusal it passes on needs no filter design."""
    assert (
        printed_by("import sys\nimport server.robotd.estop_listener\nprint('scipy.signal' in sys.modules)\n") == "False"
    )
