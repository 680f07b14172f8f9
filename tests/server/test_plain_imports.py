"""Issue 15 §2: the modules that used to look their dependencies up with `importlib` (and, in prescription
validation, carried on without them) now import them plainly, so a broken dependency fails loudly.

Each case runs in a fresh interpreter in which one dependency is made unimportable (`sys.modules[name] = None`
makes every later import of it raise ImportError), then imports the module under test and uses it."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _run_with_broken(module: str, code: str) -> subprocess.CompletedProcess[str]:
    script = f"import sys\nsys.modules[{module!r}] = None\n" + textwrap.dedent(code)
    return subprocess.run(
        [sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=300, check=False
    )


def _assert_import_error_names(result: subprocess.CompletedProcess[str], module: str) -> None:
    assert result.returncode != 0, f"a broken {module} went unnoticed; output: {result.stdout!r} {result.stderr!r}"
    assert "ImportError" in result.stderr or "ModuleNotFoundError" in result.stderr, result.stderr
    assert module in result.stderr, result.stderr


def test_the_command_line_fails_loudly_when_the_realtime_stack_cannot_be_imported(tmp_path: Path) -> None:
    # The commands load their science when they run (issue 21 §7), so the failure comes with the command that
    # needs the module; the command is still listed, never quietly missing.
    prescription = tmp_path / "prescription.json"
    prescription.write_text('{"segments": []}')
    result = _run_with_broken(
        "server.realtime.loop",
        f"""
        import sys
        from typer.testing import CliRunner
        from server.cli.main import app
        listed = CliRunner().invoke(app, ["realtime", "--help"]).output
        print("check listed" if "check" in listed else "check missing")
        sys.argv = ["ssp-rehab", "realtime", "check", {str(prescription)!r}]
        app()
        print("the command ran")
        """,
    )
    _assert_import_error_names(result, "server.realtime.loop")
    assert "check listed" in result.stdout
    assert "the command ran" not in result.stdout


@pytest.mark.parametrize("core_module", ["core.cues", "core.washout"])
def test_a_prescription_is_never_stored_unchecked_when_a_core_validator_is_missing(core_module: str) -> None:
    # Before issue 15 §2 the validator logged a warning and stored the prescription without that check.
    result = _run_with_broken(
        core_module,
        """
        from core.plan.prescription import parse_prescription
        cue = {"kind": "sine", "axis": "y", "amplitude_m_s2": 0.5, "frequency_hz": 0.25}
        parse_prescription({"segments": [{"cue": cue, "duration_s": 5.0}]})
        print("stored unchecked")
        """,
    )
    _assert_import_error_names(result, core_module)
    assert "stored unchecked" not in result.stdout


def test_the_schema_is_never_loaded_with_a_domain_missing() -> None:
    result = _run_with_broken(
        "server.reviews.models",
        """
        from server.db import load_models
        print(sorted(load_models().tables))
        """,
    )
    _assert_import_error_names(result, "server.reviews.models")
