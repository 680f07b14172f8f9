"""Issue 20 defect 19: the session-control lease belongs to a console, and the web processes of one
`serve --workers N` are one console (their links name the same console id)."""

from __future__ import annotations

import pytest

from server.errors import ConflictError
from server.robotd.consoles import CONSOLE_LOST, ConsoleLinks


def daemon() -> ConsoleLinks:
    return ConsoleLinks("twin-1", stall_tolerance_s=60.0)


def test_every_web_process_of_one_console_may_start_and_another_console_may_not() -> None:
    robot = daemon()
    robot.opened("first", 101, "serve-a")
    robot.opened("second", 102, "serve-a")
    robot.opened("other", 201, "serve-b")
    robot.take_lease("first")
    robot.take_lease("second")  # before: 409 "another console (process 101) holds the session control"
    robot.take_lease("first")
    with pytest.raises(ConflictError, match=r"another console \(process 10[12]\) holds the session control"):
        robot.take_lease("other")


def test_the_lease_is_free_once_the_consoles_last_link_ends() -> None:
    robot = daemon()
    robot.opened("first", 101, "serve-a")
    robot.opened("second", 102, "serve-a")
    robot.opened("other", 201, "serve-b")
    robot.take_lease("first")
    robot.closed("first")
    with pytest.raises(ConflictError):
        robot.take_lease("other")  # the console still has a live process
    robot.closed("second")
    robot.take_lease("other")


def test_links_that_name_no_console_are_each_their_own() -> None:
    robot = daemon()
    robot.opened("first", 101)
    robot.opened("second", 102)
    robot.take_lease("first")
    with pytest.raises(ConflictError):
        robot.take_lease("second")


def test_a_console_is_lost_when_its_link_ends_and_lives_while_it_beats() -> None:
    robot = daemon()
    robot.opened("first", 101, "serve-a")
    robot.beat("first")
    assert robot.lost("first") is None
    assert robot.lost("first", closed="first") == CONSOLE_LOST
    robot.closed("first")
    assert robot.lost("first") == CONSOLE_LOST
    silent = ConsoleLinks("twin-1", stall_tolerance_s=0.0)
    silent.opened("first", 101, "serve-a")
    silent.links["first"].last_beat_s -= 1.0  # a beat a second ago, with no tolerance
    assert "stopped answering" in (silent.lost("first") or "")
