"""The real-time worker process (spawned by `WorkerClient`): it owns the HAL and runs the fixed-rate loop.

Each iteration: wait for the deadline → the heartbeat relay's beat count (server.realtime.heartbeat) →
the emergency-stop flag in shared memory (never queued behind anything) → commands from the pipe (a few
per tick; the pipe closing means the service is gone) → `TickPipeline.tick` → the tick's record into the
telemetry ring and behind the seqlock. Replies go back on their own pipe; events go into their own
shared-memory ring at once.

In the robot daemon a prescription is planned and checked by the daemon's planning process, and the
worker only takes the finished plan (`load_plan`), so the loop keeps running, and an emergency stop is
latched, during a long check. `load` (plan and check here, with the drives off) remains for direct use
of `WorkerClient`.
The worker exits on `shutdown` or when the service is gone, but only once the drives are off.
"""

from __future__ import annotations

import gc
import logging
import os
import sys
import time
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from typing import Any

from core.plan.build import PrescriptionPlan, build_plan
from core.plan.check import PrescriptionRejected
from core.plan.prescription import PrescriptionError
from core.robot import default_twin, load_twin
from server.hal.backends import make_hal
from server.realtime.loop import FixedRateLoop, configure_realtime, freeze_garbage_collector
from server.realtime.pipeline import TickPipeline, compile_tick_path
from server.realtime.shm import ControlBlock, Seqlock, SharedRing, memory_barrier
from server.realtime.supervisor import SupervisorConfig, TransitionRefused
from server.realtime.telemetry import EVENT_DTYPE, TELEMETRY_DTYPE, StopReason, SupervisorState, encode_event

LOAD_STATES = (SupervisorState.IDLE, SupervisorState.READY, SupervisorState.STOPPED)
COMMANDS_PER_TICK = 4
IDLE_COLLECT_PERIOD_S = 10.0
WORKER_FIFO_PRIORITY = 80

log = logging.getLogger("ssp_rehab.realtime")


@dataclass(frozen=True)
class WorkerConfig:
    twin_path: str | None
    backend: str
    control_rate_hz: int
    supervisor: dict[str, Any]
    control_name: str
    state_name: str
    telemetry_name: str
    telemetry_capacity: int
    events_name: str
    events_capacity: int
    cpu: int | str | None = "auto"  # server.realtime.scheduling: auto, none or a CPU number
    fifo_priority: int | None = WORKER_FIFO_PRIORITY  # None: do not ask for SCHED_FIFO (benchmarks)
    hal_options: dict[str, Any] = field(default_factory=dict)


class Worker:
    def __init__(self, config: WorkerConfig, commands: Connection, replies: Connection) -> None:
        self.config = config
        self.commands, self.replies = commands, replies
        self.control = ControlBlock(config.control_name)
        self.state = Seqlock(TELEMETRY_DTYPE, config.state_name)
        self.telemetry = SharedRing(TELEMETRY_DTYPE, config.telemetry_capacity, config.telemetry_name)
        self.events = SharedRing(EVENT_DTYPE, config.events_capacity, config.events_name)
        self.twin = load_twin(config.twin_path) if config.twin_path else default_twin()
        self.supervisor_config = SupervisorConfig.from_dict(config.supervisor)
        compile_tick_path(self.twin, config.control_rate_hz, self.supervisor_config)
        period = 1.0 / config.control_rate_hz
        self.hal = make_hal(config.backend, self.twin, period, **config.hal_options)
        self.hal.configure()
        self.hal.home()
        self.pipeline = TickPipeline(self.twin, self.hal, config.control_rate_hz, self.supervisor_config, self.emit)
        self.loop = FixedRateLoop(config.control_rate_hz)
        self._estop_seen = int(self.control.fields["estop_requests"][0])
        self._estop_requests = self.control.fields["estop_requests"]
        self._estop_times = self.control.fields["estop_request_ns"]
        self._relay_beats = self.control.fields["relay_beats"]
        self._relay_beats_seen = int(self._relay_beats[0])
        self.service_gone = False
        self.shutdown_requested = False
        self._next_collect_s = 0.0
        self.realtime: dict[str, Any] = {}  # what configure_realtime obtained (the `realtime_setup` command)

    # --- events and replies -----------------------------------------------------------------------

    def emit(self, kind: str, details: dict[str, Any], detector: str | None = None) -> None:
        slot = self.events.slot()
        slot["tick"] = self.pipeline.tick_index
        slot["tick_time_s"] = self.pipeline.tick_time_s  # this tick's stamp: the clock of session_time_s
        slot["utc_s"] = time.time()
        encode_event(slot, kind, details, detector)
        self.events.publish()

    def _reply(self, request_id: int, ok: bool, result: Any) -> None:
        if self.service_gone:
            return
        try:
            self.replies.send((request_id, ok, result))
        except (OSError, EOFError):
            self._lose_service()

    # --- commands ---------------------------------------------------------------------------------

    def _poll_commands(self) -> None:
        for _ in range(COMMANDS_PER_TICK):
            try:
                if not self.commands.poll(0):
                    return
                message = self.commands.recv()
            except (EOFError, OSError):
                self._lose_service()
                return
            self._handle(*message)

    def _lose_service(self) -> None:
        if not self.service_gone:
            self.service_gone = True
            self.emit("service_lost", {})
            self.pipeline.service_lost()

    def _handle(self, request_id: int, name: str, payload: Any) -> None:
        pipeline = self.pipeline
        if name == "estop":
            pipeline.emergency_stop(payload)
            return
        try:
            result: Any = None
            if name in ("load", "load_plan", "start"):
                self._refuse_after_estop(name, (payload or {}).get("estop_generation"))
            if name == "load":
                result = self._load(payload["prescription"], payload.get("patient"))
            elif name == "load_plan":
                result = self._load_plan(payload["plan"], payload["report"])
            elif name == "realtime_setup":
                result = self.realtime
            elif name == "service_lost":  # the daemon lost the console that controls the run
                self.emit("service_lost", payload or {})
                pipeline.service_lost()
            elif name == "recording_failed":  # the daemon cannot write the run's journal
                pipeline.recording_failed(payload or {})
            elif name == "latch_fault":  # a fresh worker after a lost worker or daemon
                pipeline.latch_fault(StopReason[str(payload["reason"]).upper()], payload.get("details") or {})
            elif name in ("start", "pause", "resume", "stop", "reset"):
                getattr(pipeline, name)()
            elif name == "shutdown":
                self.shutdown_requested = True
                pipeline.supervisor.controlled_stop(StopReason.OPERATOR, {})
            else:
                raise ValueError(f"command = {name!r}: unknown")
            self._reply(request_id, True, result)
        except PrescriptionRejected as rejected:
            self._reply(request_id, False, {"type": "PrescriptionRejected", **rejected.to_dict()})
        except PrescriptionError as error:
            self._reply(
                request_id,
                False,
                {"type": "PrescriptionError", "field": error.field, "value": repr(error.value), "limit": error.limit},
            )
        except TransitionRefused as refused:
            self._reply(request_id, False, {"type": "TransitionRefused", "message": str(refused)})
        except Exception as error:  # a bad command must never take the loop down
            self._reply(request_id, False, {"type": type(error).__name__, "message": str(error)})

    def _refuse_after_estop(self, command: str, estop_generation: int | None) -> None:
        """A load or start asked for before the latest emergency-stop request is refused, even after a reset:
        the stop cancelled it (issue 20, defect 2). The flag was read at the top of this tick."""
        if estop_generation is None:
            return
        requests = int(self._estop_requests[0])
        if requests != int(estop_generation):
            raise TransitionRefused(
                command,
                self.pipeline.supervisor.state,
                f"cancelled: an emergency stop was requested after it (request {requests}; the {command} was asked "
                f"for after request {int(estop_generation)})",
            )

    def _load_plan(self, plan: PrescriptionPlan, report: dict[str, Any]) -> dict[str, Any]:
        """Take a plan the daemon's planning process made and checked: the loop never stops for it."""
        try:
            self.pipeline.load(plan)
        finally:
            self.loop.rebase()  # building the segments' streaming objects may take a few periods
        self.emit("prescription_checked", report)
        return report

    def _load(self, prescription: dict[str, Any], patient: dict[str, Any] | None) -> dict[str, Any]:
        self.pipeline.supervisor.require("load", *LOAD_STATES)
        try:
            checked = build_plan(
                prescription,
                self.twin,
                control_rate_hz=self.config.control_rate_hz,
                config=self.supervisor_config,
                patient=patient,
            )
            report = checked.accepted()
            self.pipeline.load(checked.plan)
        finally:
            self.loop.rebase()  # planning and the check took many periods; the drives are off, nothing was late
        self.emit("prescription_checked", report.to_dict())
        return report.to_dict()

    # --- the loop ---------------------------------------------------------------------------------

    def run(self) -> None:
        setup = configure_realtime(self.config.cpu, self.config.fifo_priority)
        self.realtime = setup.to_dict()
        for refusal in setup.refusals:
            log.warning("real-time setup: %s", refusal)
        log.info("real-time worker on CPU %s, SCHED_FIFO priority %s", setup.cpu, setup.fifo_priority)
        self.emit(
            "worker_started",
            {
                "pid": os.getpid(),
                "backend": self.config.backend,
                "control_rate_hz": self.config.control_rate_hz,
                "cpu": setup.cpu,
                "fifo_priority": setup.fifo_priority,
                "refusals": setup.refusals,
            },
        )
        freeze_garbage_collector()
        self.control.fields["worker_pid"] = os.getpid()
        self.loop.rebase()
        record, pipeline = self.pipeline.record, self.pipeline
        ready = self.control.fields["worker_ready"]
        while True:
            lateness = self.loop.wait()
            started = time.perf_counter_ns()
            relay_beats = int(self._relay_beats[0])
            if relay_beats != self._relay_beats_seen:
                self._relay_beats_seen = relay_beats
                pipeline.heartbeat()
            requests = int(self._estop_requests[0])
            if requests != self._estop_seen:
                self._estop_seen = requests
                memory_barrier()  # the request's time was stored before its counter: read it after
                pipeline.emergency_stop(int(self._estop_times[0]))
            if not self.service_gone:
                self._poll_commands()
            pipeline.tick(lateness)
            record["tick_compute_us"] = (time.perf_counter_ns() - started) * 1e-3
            self.telemetry.push(record)
            self.state.write(record)
            if not ready[0]:  # ready once a first state is published: a client never reads a blank one
                ready[0] = 1
            if not pipeline.supervisor.drives_enabled:
                if self.shutdown_requested or self.service_gone:
                    break
                self._collect_when_idle()
        self.emit("worker_stopped", {"service_gone": self.service_gone})
        self.hal.shutdown()

    def _collect_when_idle(self) -> None:
        """With the drives off a collection pause harms nobody; cycles would pile up otherwise."""
        now = time.monotonic()
        if now >= self._next_collect_s:
            self._next_collect_s = now + IDLE_COLLECT_PERIOD_S
            gc.collect()
            self.loop.rebase()

    def close(self) -> None:
        for block in (self.control, self.state, self.telemetry, self.events):
            block.close()


def worker_entry(config: WorkerConfig, commands: Connection, replies: Connection) -> None:
    """Process entry point (multiprocessing spawn)."""
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s worker %(levelname)s %(message)s")
    worker = Worker(config, commands, replies)
    try:
        worker.run()
    finally:
        worker.close()
