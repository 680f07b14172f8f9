"""Browser end-to-end fixtures: Debian's chromium (never a downloaded browser) and a real `ssp-rehab serve`
on free loopback ports with a temporary data directory and the simulator backend."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    # WebGL for the 3D view without a GPU: the software rasteriser must be allowed explicitly.
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
]
ARTIFACTS = Path(__file__).resolve().parents[2] / "artifacts" / "e2e"
ADMIN = ("e2e-admin", "e2e-password-1")
SERVICE_START_TIMEOUT_S = 300.0  # the worker compiles its kernels and builds the MuJoCo model at start


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _cli() -> list[str]:
    return [sys.executable, "-m", "server.cli.main"]


@pytest.fixture(scope="session")
def chromium_path() -> Path:
    if not CHROMIUM.exists():
        pytest.skip(f"{CHROMIUM} is absent: install Debian's chromium package to run the browser tests")
    return CHROMIUM


@pytest.fixture(scope="session")
def console_service(tmp_path_factory: pytest.TempPathFactory, chromium_path: Path) -> Iterator[dict[str, object]]:
    data_dir = tmp_path_factory.mktemp("e2e-data")
    port, viz_port = free_port(), free_port()
    env = {
        **os.environ,
        "SSP_REHAB_VIZ_PORT": str(viz_port),
        "SSP_REHAB_DATA_DIR": str(data_dir),
        # A shared 2-core CI machine cannot hold 1 kHz beside a browser; the flow under test is the console's.
        "SSP_REHAB_CONTROL_RATE_HZ": os.environ.get("SSP_REHAB_E2E_CONTROL_RATE_HZ", "250"),
    }
    root = Path(__file__).resolve().parents[2]
    subprocess.run(
        [*_cli(), "create-user", "--username", ADMIN[0], "--password", ADMIN[1], "--role", "admin",
         "--data-dir", str(data_dir)],
        check=True, cwd=root, env=env, capture_output=True,
    )  # fmt: skip
    backend = os.environ.get("SSP_REHAB_E2E_BACKEND", "kinematic")
    log = (data_dir / "serve.log").open("w")
    process = subprocess.Popen(
        [*_cli(), "serve", "--port", str(port), "--data-dir", str(data_dir), "--backend", backend],
        cwd=root, env=env, stdout=log, stderr=subprocess.STDOUT,
    )  # fmt: skip
    base_url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + SERVICE_START_TIMEOUT_S
    try:
        while True:
            if process.poll() is not None:
                raise RuntimeError(
                    f"ssp-rehab serve exited ({process.returncode}): {(data_dir / 'serve.log').read_text()[-3000:]}"
                )
            try:
                if httpx.get(f"{base_url}/api/v1/health", timeout=2.0).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                raise RuntimeError(f"ssp-rehab serve did not answer within {SERVICE_START_TIMEOUT_S} s")
            time.sleep(0.5)
        yield {
            "base_url": base_url,
            "viz_port": viz_port,
            "backend": backend,
            "log": data_dir / "serve.log",
            "database_url": f"sqlite:///{(data_dir / 'ssp-rehab.sqlite3').resolve()}",
        }
    finally:
        process.terminate()
        try:
            process.wait(60)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)
        log.close()
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        (ARTIFACTS / "serve.log").write_text((data_dir / "serve.log").read_text())


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Iterator[pytest.TestReport]:
    """Keeps each phase's report on the test item, so fixtures can save a screenshot when a test failed."""
    report = yield
    setattr(item, f"rep_{report.when}", report)
    return report
