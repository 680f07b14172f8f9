"""Issue 20 defect 19: one robot, one 3D view. With `serve --workers 2` the second web process found the
configured port taken, and viser quietly opened a second view on the next port (8482)."""

from __future__ import annotations

import socket
from pathlib import Path

from benchmarks.fault_harness import free_port
from core.robot import default_twin
from server.settings import Settings
from server.viz.view import start_view


def _listening(port: int) -> bool:
    with socket.socket() as probe:
        probe.settimeout(2.0)
        return probe.connect_ex(("127.0.0.1", port)) == 0


def test_a_second_web_process_starts_no_second_view(tmp_path: Path) -> None:
    port = free_port()
    settings = Settings(data_dir=tmp_path, viz_port=port)
    twin = default_twin()
    first = start_view(settings, twin, None)
    assert first is not None and first.port == port
    try:
        second = start_view(settings, twin, None)
        try:
            assert second is None, f"a second 3D view runs on port {second.port if second else None}"
            assert not _listening(port + 1)
        finally:
            if second is not None:
                second.stop()
    finally:
        first.stop()
