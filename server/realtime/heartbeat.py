"""The heartbeat relay: a small process that beats to the worker on the service's behalf.

The service's own threads share its GIL with the API's request threads, and under load a thread can wait
longer than the worker's 100 ms watchdog. That must not end a patient's session, while a dead or hung
service must. So the relay, a process with no such neighbours, advances `relay_beats` in the control block
every period as long as:
1. the service is alive: the relay holds one end of a pipe whose other end only the service holds, so the
   service's death is an EOF here at once (and the worker sees its own command pipe close too);
2. the service shows life: its `service_beats` counter advanced within `stall_tolerance_s`.
A dead service stops the beats at once, a hung one after the tolerance, a momentarily busy one not at all.
The worker keeps its 100 ms watchdog on the relay's beats.
"""

from __future__ import annotations

import logging
import os
import time
from multiprocessing.connection import Connection

from server.realtime.shm import ControlBlock

SERVICE_STALL_TOLERANCE_S = 0.5
RELAY_FIFO_PRIORITY = 60  # above ordinary processes, below the worker's loop

log = logging.getLogger(__name__)


def relay_heartbeats(
    control: ControlBlock, service_link: Connection, period_s: float, stall_tolerance_s: float
) -> None:
    """Beat every `period_s` while the service is alive and showing life; return when the service is gone."""
    fields = control.fields
    last_service_beats = int(fields["service_beats"][0])
    last_change = time.monotonic()
    while True:
        if service_link.poll(period_s):  # data or EOF: the service said goodbye or died
            return
        now = time.monotonic()
        service_beats = int(fields["service_beats"][0])
        if service_beats != last_service_beats:
            last_service_beats, last_change = service_beats, now
        if now - last_change <= stall_tolerance_s:
            fields["relay_beats"] += 1


def relay_entry(control_name: str, service_link: Connection, period_s: float, stall_tolerance_s: float) -> None:
    """Process entry point (multiprocessing spawn)."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RELAY_FIFO_PRIORITY))
    except (OSError, AttributeError) as error:
        log.info("heartbeat relay runs without real-time priority: %s", error)
    control = ControlBlock(control_name)
    try:
        relay_heartbeats(control, service_link, period_s, stall_tolerance_s)
    finally:
        control.close()
