"""`benchmarks.results.record`: the dated section of RESULTS.md is replaced whatever the figures hold."""

from __future__ import annotations

from pathlib import Path

from benchmarks.results import record


def test_record_replaces_a_section_whose_figures_hold_backslashes(tmp_path: Path) -> None:
    """A rejection reason with a non-ASCII dash is dumped as "\\u2013": as a regex replacement it was a bad
    escape (re.error), so `bench cueing --write-results` could not record a refused classical plan."""
    path = tmp_path / "RESULTS.md"
    path.write_text("# Results\n\n## cueing\n\nold\n\n## faults\n\nkept\n")
    record("cueing", {"reason": "right slider 4 – left slider 4", "path": "C:\\new"}, path=path)
    text = path.read_text()
    assert "old" not in text and "\\u2013" in text and "C:\\\\new" in text
    assert text.index("## cueing") < text.index("## faults") and "kept" in text
