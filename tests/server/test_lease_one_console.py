"""Issue 20 defect 19: the session-control lease belongs to a console, and the web processes of one
`serve --workers N` are one console (their links name the same console id)."""

from __future__ import annotations

from typing import Any, cast

import pytest

from server.errors import ConflictError
from server.robotd.daemon import RobotDaemon


def daemon() -> RobotDaemon:
    # The lease touches neither the worker nor the database.
    return RobotDaemon(robot="twin-1", worker=cast(Any, object()), database=cast(Any, None), journal_dir=None)


def test_every_web_process_of_one_console_may_start_and_another_console_may_not() -> None:
    robot = daemon()
    robot.link_opened("first", 101, "serve-a")
    robot.link_opened("second", 102, "serve-a")
    robot.link_opened("other", 201, "serve-b")
    robot._take_lease("first")
    robot._take_lease("second")  # before: 409 "another console (process 101) holds the session control"
    robot._take_lease("first")
    with pytest.raises(ConflictError, match=r"another console \(process 10[12]\) holds the session control"):
        robot._take_lease("other")


def test_the_lease_is_free_once_the_consoles_last_link_ends() -> None:
    robot = daemon()
    robot.link_opened("first", 101, "serve-a")
    robot.link_opened("second", 102, "serve-a")
    robot.link_opened("other", 201, "serve-b")
    robot._take_lease("first")
    robot.link_closed("first")
    with pytest.raises(ConflictError):
        robot._take_lease("other")  # the console still has a live process
    robot.link_closed("second")
    robot._take_lease("other")


def test_links_that_name_no_console_are_each_their_own() -> None:
    robot = daemon()
    robot.link_opened("first", 101)
    robot.link_opened("second", 102)
    robot._take_lease("first")
    with pytest.raises(ConflictError):
        robot._take_lease("second")
