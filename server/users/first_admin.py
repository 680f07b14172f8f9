"""The first start's hint: a command to copy that creates the first admin and asks for the password (so
it never lands in the shell history), naming the `ssp-rehab` of this very installation, which need not
be on the PATH (a virtual environment's bin/ often is not)."""

from __future__ import annotations

import shlex
import shutil
import sys
from pathlib import Path

CLI_NAME = "ssp-rehab"


def cli_command() -> list[str]:
    """How to run this installation's CLI: the script beside this interpreter, else the one on the PATH,
    else the module through this interpreter."""
    beside = Path(sys.executable).parent / CLI_NAME
    if beside.is_file():
        return [str(beside)]
    on_path = shutil.which(CLI_NAME)
    if on_path:
        return [on_path]
    return [sys.executable, "-m", "server.cli.main"]


def first_admin_command(data_dir: Path) -> str:
    """The shell command (quoted, copyable) that creates the first admin; it prompts for the password."""
    words = [*cli_command(), "create-user", "--username", "admin", "--role", "admin", "--data-dir", str(data_dir)]
    return shlex.join(words)
