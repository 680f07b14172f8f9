"""Shared fixtures."""

from __future__ import annotations

import pytest

from core.robot import SSPRobot, TwinRobot, default_twin, paper_robot


@pytest.fixture(scope="session")
def robot() -> SSPRobot:
    return paper_robot()


@pytest.fixture(scope="session")
def twin() -> TwinRobot:
    return default_twin()
