"""Write one benchmark's dated figures into its own section of benchmarks/RESULTS.md."""

from __future__ import annotations

import datetime as dt
import json
import platform
import re
from pathlib import Path
from typing import Any

RESULTS_PATH = Path(__file__).with_name("RESULTS.md")
HEADER = "# Benchmark results\n\nDated figures written by `ssp-rehab bench <name> --write-results`.\n"


def machine_summary() -> str:
    """The machine and how busy it was: figures from a loaded machine read differently."""
    import os

    load_1min = os.getloadavg()[0]
    return (
        f"{platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}, "
        f"load average {load_1min:.1f} at the end of the run"
    )


def record(name: str, figures: dict[str, Any], *, path: Path = RESULTS_PATH) -> None:
    """Replace the `## <name>` section with today's figures; other sections stay as they are."""
    text = path.read_text() if path.exists() else HEADER
    today = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    section = (
        f"## {name}\n\n_Measured {today} on {machine_summary()}._\n\n"
        f"```json\n{json.dumps(figures, indent=2, default=str)}\n```\n"
    )
    pattern = re.compile(rf"^## {re.escape(name)}\n.*?(?=^## |\Z)", re.S | re.M)
    # A function, not a template: the figures' JSON holds backslashes ("\u2013"), not regex escapes.
    text = pattern.sub(lambda _: section + "\n", text) if pattern.search(text) else text.rstrip() + "\n\n" + section
    path.write_text(text)
