"""Shared fixtures."""

from __future__ import annotations

import httpx
import pytest

from core.robot import SSPRobot, TwinRobot, default_twin, paper_robot

# httpx's default 5 s read timeout failed a CI run: a login took longer while the 2-core machine was loaded.
# Every test's HTTP call that names no timeout waits as generously as the tests' other event-based waits.
GENEROUS_HTTP_TIMEOUT_S = 60.0
for _phase in ("connect", "read", "write", "pool"):
    setattr(httpx._config.DEFAULT_TIMEOUT_CONFIG, _phase, GENEROUS_HTTP_TIMEOUT_S)


@pytest.fixture(scope="session")
def robot() -> SSPRobot:
    return paper_robot()


@pytest.fixture(scope="session")
def twin() -> TwinRobot:
    return default_twin()


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """The browser tests run last: their console is session-scoped, and its real-time worker would hold one
    of the two CPU claims through every later test, leaving the fault tests' consoles unpinned."""
    items.sort(key=lambda item: "/tests/e2e/" in str(item.path))  # a stable sort keeps every other order
