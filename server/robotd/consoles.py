"""The link watch: which consoles are attached to the robot daemon and alive, and the session-control
lease (issue 15 §2): one console at a time may start motion. It holds the lease while one of its links
lives and beats; the web processes of one `serve --workers N` are one console (issue 20, defect 19: a
start on an idle robot landed on another of its processes and was refused). The daemon's run controller
(server.robotd.daemon) asks it whether the console controlling a run is lost."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

from server.errors import ConflictError

WEB_STALL_TOLERANCE_S = 1.0  # a controlling console silent this long is treated as gone
# Why a run ended interrupted when its console exited (a controlled stop either way): its link ended, or the
# daemon was stopped with its run still in motion (then "... (SIGTERM)").
CONSOLE_LOST = "the console controlling the run was lost (its process ended)"


@dataclass
class LinkState:
    """One attached console: alive while its link is attached and it beats."""

    pid: int | None = None  # the console's process, to name it in a refusal
    console: str | None = None  # the console it serves: the web processes of one `serve` share one
    last_beat_s: float = field(default_factory=time.monotonic)


class ConsoleLinks:
    """The links of the consoles attached to one robot, and who holds its session-control lease. The
    caller serialises changes (the daemon's lock)."""

    def __init__(self, robot: str, stall_tolerance_s: float = WEB_STALL_TOLERANCE_S) -> None:
        self.robot = robot
        self.stall_tolerance_s = stall_tolerance_s
        self.links: dict[str, LinkState] = {}
        self.lease_holder: str | None = None

    def opened(self, link_id: str, pid: int | None = None, console: str | None = None) -> None:
        self.links[link_id] = LinkState(pid, console=console)

    def beat(self, link_id: str) -> None:
        link = self.links.get(link_id)
        if link is not None:
            link.last_beat_s = time.monotonic()

    def closed(self, link_id: str) -> None:
        self.links.pop(link_id, None)
        if self.lease_holder is not None and not any(
            self.console_of(other) == self.lease_holder for other in self.links
        ):
            self.lease_holder = None  # the holder's last link ended

    def console_of(self, link_id: str) -> str:
        """The console a link serves (its own id when it named none)."""
        link = self.links.get(link_id)
        return link.console if link is not None and link.console else link_id

    def take_lease(self, controller: str | None) -> None:
        """The console of link `controller` takes the lease; refused while another console holds it and
        lives. None: a start from inside the daemon's process (tests), which needs no lease."""
        if controller is None:
            return
        console = self.console_of(controller)
        now = time.monotonic()
        holders = [
            link
            for link_id, link in self.links.items()
            if self.lease_holder is not None
            and self.console_of(link_id) == self.lease_holder
            and now - link.last_beat_s <= self.stall_tolerance_s
        ]
        if holders and self.lease_holder != console:
            raise ConflictError(
                f"another console (process {holders[0].pid}) holds the session control of robot {self.robot!r}: "
                "start motion there, or close it first",
                field="lease",
            )
        self.lease_holder = console

    def lost(self, controller: str, closed: str | None = None) -> str | None:
        """Why the console of link `controller` is lost, in words (its link ended, as `closed` or before;
        or it fell silent); None while it lives."""
        link = self.links.get(controller)
        if controller == closed or link is None:
            return CONSOLE_LOST
        if time.monotonic() - link.last_beat_s > self.stall_tolerance_s:
            return f"the console controlling the run stopped answering for over {self.stall_tolerance_s:g} s"
        return None
