"""The real-time worker process (spawned by `WorkerClient`): it owns the HAL and runs the fixed-rate loop.

Each iteration: wait for the deadline → the heartbeat relay's beat count (server.realtime.heartbeat) →
the emergency-stop flag in shared memory (never queued behind anything) → commands from the pipe (a few
per tick; the pipe closing means the service is gone) → `TickPipeline.tick` → the tick's record into the
telemetry ring and behind the seqlock. Replies go back on their own pipe; events go into their own
shared-memory ring at once.

The worker plans and checks nothing: it takes a checked plan (`load_plan`) and the checked transitions
(the approach with `start`, `pause`, `resume`), made by the robot daemon and its planning process, so the
loop keeps running, and an emergency stop is latched, during a long check.
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

from core.plan.build import PrescriptionPlan
from core.robot import default_twin, load_twin
from server import messages as msg
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
        for ring in (self.telemetry, self.events):
            ring.prepare_to_produce()
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

    def _reply(self, reply: msg.WorkerReply) -> None:
        if self.service_gone:
            return
        try:
            self.replies.send(reply)
        except (OSError, EOFError):
            self._lose_service()

    # --- commands ---------------------------------------------------------------------------------

    def _poll_commands(self) -> None:
        for _ in range(COMMANDS_PER_TICK):
            try:
                if not self.commands.poll(0):
                    return
                request: msg.WorkerRequest = self.commands.recv()
            except (EOFError, OSError):
                self._lose_service()
                return
            self._handle(request)

    def _lose_service(self) -> None:
        if not self.service_gone:
            self.service_gone = True
            self.emit("service_lost", {})
            self.pipeline.service_lost()

    def _handle(self, request: msg.WorkerRequest) -> None:
        command, pipeline = request.command, self.pipeline
        if isinstance(command, msg.EmergencyStop):
            pipeline.emergency_stop(None)
            return
        try:
            self._reply(msg.WorkerReply(request.request_id, self._obey(command)))
        except Exception as error:  # a bad command is refused; it never takes the loop down
            self._reply(msg.WorkerReply(request.request_id, refusal=msg.refusal_of(error)))

    def _obey(self, command: msg.WorkerCommand) -> Any:
        pipeline = self.pipeline
        match command:
            case msg.LoadPlan(plan=plan, report=report, estop_generation=generation):
                self._refuse_after_estop("load_plan", generation)
                return self._load_plan(plan, report)
            case msg.StartMotion(approach=approach, estop_generation=generation):
                self._refuse_after_estop("start", generation)
                pipeline.start(approach)
            case msg.PauseMotion(transition=transition):
                pipeline.pause(transition)
            case msg.ResumeMotion(transition=transition):
                pipeline.resume(transition)
            case msg.StopMotion():
                pipeline.stop()
            case msg.ResetFaults():
                pipeline.reset()
            case msg.RealtimeSetup():
                return self.realtime
            case msg.ServiceLost(reason=reason):  # the daemon lost the console that controls the run
                self.emit("service_lost", {"reason": reason})
                pipeline.service_lost()
            case msg.RecordingFailed(details=details):  # the daemon cannot write the run's journal
                pipeline.recording_failed(details)
            case msg.LatchFault(reason=reason, details=details):  # a fresh worker after a lost worker or daemon
                pipeline.latch_fault(StopReason[reason.upper()], details)
            case msg.Shutdown():
                self.shutdown_requested = True
                pipeline.supervisor.controlled_stop(StopReason.OPERATOR, {})
            case _:
                raise ValueError(f"command = {command!r}: unknown")
        return None

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

    def _load_plan(self, plan: PrescriptionPlan, report: dict[str, Any] | None) -> dict[str, Any]:
        """Take a plan the daemon's planning process made and checked: the loop never stops for it."""
        if not report:
            raise TransitionRefused("load", self.pipeline.supervisor.state, "the plan comes without its check report")
        try:
            self.pipeline.load(plan)
        finally:
            self.loop.rebase()  # building the segments' streaming objects may take a few periods
        self.emit("prescription_checked", report)
        return report

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
