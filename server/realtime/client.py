"""`WorkerClient`: the service's handle on one robot's real-time worker process.

It creates the shared memory (control flags, latest-state seqlock, telemetry and event rings) and the
command and reply pipes, spawns the worker and the heartbeat relay (server.realtime.heartbeat), and keeps
a background thread showing the relay that this process is alive. The
emergency stop is written straight into shared memory, where the worker looks every tick, so it never
waits behind a command, a reply or a busy service; it is also sent down the pipe as a second path.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import multiprocessing
import os
import sys
import threading
import time
from typing import Any

import numpy as np

from core.plan.config import DEFAULT_CONTROL_RATE_HZ
from server import messages as msg
from server.hal.backends import BACKENDS
from server.realtime.heartbeat import SERVICE_STALL_TOLERANCE_S, relay_entry
from server.realtime.loop import validate_control_rate
from server.realtime.shm import ControlBlock, Seqlock, SharedRing
from server.realtime.supervisor import SupervisorConfig
from server.realtime.telemetry import EVENT_DTYPE, TELEMETRY_DTYPE, decode_events, state_dict
from server.realtime.worker import WORKER_FIFO_PRIORITY, WorkerConfig, worker_entry

HEARTBEAT_SWITCH_INTERVAL_S = 0.001
HEARTBEAT_PERIOD_S = 0.02  # five heartbeats per 100 ms watchdog window
HEARTBEAT_FIFO_PRIORITY = 10  # below the worker's loop (80)
TELEMETRY_CAPACITY = 1 << 15  # 32 s at 1 kHz between drains
EVENTS_CAPACITY = 1 << 10


log = logging.getLogger("ssp_rehab.realtime")


class WorkerError(RuntimeError):
    """The worker could not be started, died, or did not answer."""


class WorkerClient:
    def __init__(
        self,
        twin_path_or_none: str | None,
        backend: str,
        control_rate_hz: int = DEFAULT_CONTROL_RATE_HZ,
        *,
        supervisor_config: SupervisorConfig | None = None,
        cpu: int | str | None = "auto",
        fifo_priority: int | None = WORKER_FIFO_PRIORITY,
        hal_options: dict[str, Any] | None = None,
        heartbeat_period_s: float = HEARTBEAT_PERIOD_S,
    ) -> None:
        if backend not in BACKENDS:
            raise ValueError(f"backend = {backend!r}: must be one of {list(BACKENDS)}")
        self.twin_path = twin_path_or_none
        self.backend = backend
        self.control_rate_hz = validate_control_rate(control_rate_hz)
        self.supervisor_config = supervisor_config or SupervisorConfig()
        self.cpu = cpu
        self.fifo_priority = fifo_priority
        self.realtime_setup: dict[str, Any] = {}  # the worker's CPU, SCHED_FIFO priority and refusals
        self.hal_options = hal_options or {}
        self.heartbeat_period_s = heartbeat_period_s
        self.process: multiprocessing.process.BaseProcess | None = None
        self._ids = itertools.count(1)
        self._send_lock = threading.Lock()
        self._reply_lock = threading.Lock()
        self._stop_heartbeat = threading.Event()
        self._heartbeat_thread: threading.Thread | None = None
        self._relay: multiprocessing.process.BaseProcess | None = None

    # --- lifecycle --------------------------------------------------------------------------------

    def start(self, timeout_s: float = 60.0) -> None:
        """Spawn the worker and wait until its loop runs."""
        if self.process is not None:
            raise WorkerError("start: the worker is already started")
        self.control = ControlBlock()
        self.state = Seqlock(TELEMETRY_DTYPE)
        self.telemetry = SharedRing(TELEMETRY_DTYPE, TELEMETRY_CAPACITY)
        self.events = SharedRing(EVENT_DTYPE, EVENTS_CAPACITY)
        context = multiprocessing.get_context("spawn")
        command_reader, self._commands = context.Pipe(duplex=False)
        self._replies, reply_writer = context.Pipe(duplex=False)
        config = WorkerConfig(
            twin_path=self.twin_path,
            backend=self.backend,
            control_rate_hz=self.control_rate_hz,
            supervisor=self.supervisor_config.to_dict(),
            control_name=self.control.name,
            state_name=self.state.name,
            telemetry_name=self.telemetry.name,
            telemetry_capacity=TELEMETRY_CAPACITY,
            events_name=self.events.name,
            events_capacity=EVENTS_CAPACITY,
            cpu=self.cpu,
            fifo_priority=self.fifo_priority,
            hal_options=self.hal_options,
        )
        self.process = context.Process(
            target=worker_entry, args=(config, command_reader, reply_writer), name="ssp-rehab-realtime"
        )
        self.process.start()
        command_reader.close()
        reply_writer.close()
        relay_link, self._relay_link = context.Pipe(duplex=False)
        self._relay = context.Process(
            target=relay_entry,
            args=(self.control.name, relay_link, self.heartbeat_period_s, SERVICE_STALL_TOLERANCE_S),
            name="ssp-rehab-heartbeat",
            daemon=True,
        )
        self._relay.start()
        relay_link.close()
        # Shorter GIL turns keep this process's own beat (to the relay) regular among busy API threads.
        sys.setswitchinterval(min(sys.getswitchinterval(), HEARTBEAT_SWITCH_INTERVAL_S))
        self._heartbeat_thread = threading.Thread(target=self._send_heartbeats, name="worker-heartbeat", daemon=True)
        self._heartbeat_thread.start()
        deadline = time.monotonic() + timeout_s
        while not int(self.control.fields["worker_ready"][0]):
            failure = None
            if not self.process.is_alive():
                failure = f"the worker exited during start-up (exit code {self.process.exitcode})"
            elif time.monotonic() > deadline:
                failure = f"the worker did not start within {timeout_s} s"
            if failure is not None:
                self.shutdown(timeout_s=5.0)  # frees the shared memory and the pipes
                raise WorkerError(failure)
            time.sleep(0.01)
        self.realtime_setup = self._send(msg.RealtimeSetup())

    @property
    def worker_pid(self) -> int:
        return int(self.control.fields["worker_pid"][0])

    def shutdown(self, timeout_s: float = 30.0) -> None:
        """Ask the worker to stop (it brings any motion to a controlled stop first), then free everything."""
        if self.process is None:
            return
        if self.process.is_alive():
            with contextlib.suppress(WorkerError):
                self._send(msg.Shutdown(), expect_reply=False)
            self.process.join(timeout_s)
            if self.process.is_alive():
                self.process.terminate()
                self.process.join(5.0)
        self._stop_heartbeat.set()
        if self._heartbeat_thread is not None:
            self._heartbeat_thread.join(1.0)
        if self._relay is not None:
            self._relay_link.close()  # EOF: the relay stops beating and exits
            self._relay.join(5.0)
            if self._relay.is_alive():
                self._relay.terminate()
            self._relay = None
        self._commands.close()
        self._replies.close()
        for block in (self.control, self.state, self.telemetry, self.events):
            block.close()
        self.process = None

    def __enter__(self) -> WorkerClient:
        self.start()
        return self

    def __exit__(self, *_: object) -> None:
        self.shutdown()

    # --- commands ---------------------------------------------------------------------------------

    def load_plan(self, plan: Any, report: dict[str, Any], estop_generation: int | None = None) -> dict[str, Any]:
        """Load a plan already made and checked elsewhere (the daemon's planning process)."""
        result: dict[str, Any] = self._send(
            msg.LoadPlan(plan=plan, report=report, estop_generation=estop_generation), timeout_s=30.0
        )
        return result

    def estop_request(self) -> tuple[int, float | None]:
        """(emergency stops requested so far, UTC of the latest): a start carries the count it was asked for
        under, and the worker refuses it once the count has moved on, whatever a reset did meanwhile."""
        return self.control.estop_request()

    def service_lost(self, reason: str) -> None:
        """The console controlling the run is gone: a controlled stop now (the watchdog's reaction, sooner)."""
        self._send(msg.ServiceLost(reason))

    def recording_failed(self, details: dict[str, Any]) -> None:
        """The daemon cannot record the run: a controlled stop now, with its reason."""
        self._send(msg.RecordingFailed(details))

    def latch_fault(self, reason: str, details: dict[str, Any]) -> None:
        """Show a stop that happened before this worker (`worker_lost`, `daemon_lost`) as a latched fault."""
        self._send(msg.LatchFault(reason, details))

    def start_motion(self, approach: Any, estop_generation: int | None = None) -> None:
        """Start along the checked approach (`core.plan.check.checked_approach`)."""
        self._send(msg.StartMotion(approach=approach, estop_generation=estop_generation))

    def pause(self, transition: Any) -> None:
        """Arm the checked pause (`core.plan.check.checked_pause`)."""
        self._send(msg.PauseMotion(transition))

    def resume(self, transition: Any) -> None:
        """Resume along the checked blend back into the plan (`core.plan.check.checked_resume`)."""
        self._send(msg.ResumeMotion(transition))

    def stop(self) -> None:
        self._send(msg.StopMotion())

    def reset(self) -> None:
        self._send(msg.ResetFaults())

    def emergency_stop(self) -> None:
        """Latch an emergency stop: the shared-memory flag first (read every tick), the pipe second."""
        self.control.request_estop(time.perf_counter_ns())
        # The flag is the primary path; the pipe is a second one only when no other command holds it (a
        # blocking wait here would put the caller behind that command).
        if self._reply_lock.acquire(blocking=False):
            try:
                with contextlib.suppress(WorkerError):
                    self._send_unlocked(msg.EmergencyStop())
            finally:
                self._reply_lock.release()

    # --- state and streams ------------------------------------------------------------------------

    def latest_state(self) -> dict[str, Any]:
        return state_dict(self.state.read()[0])

    def drain_telemetry(self) -> np.ndarray:
        return self.telemetry.drain()

    def drain_events(self) -> list[dict[str, Any]]:
        return decode_events(self.events.drain())

    @property
    def telemetry_lost(self) -> int:
        return self.telemetry.lost

    # --- plumbing ---------------------------------------------------------------------------------

    def _send(self, command: msg.WorkerCommand, *, expect_reply: bool = True, timeout_s: float = 5.0) -> Any:
        name = type(command).__name__
        if self.process is None:
            raise WorkerError(f"{name}: the worker is not started")
        with self._reply_lock:
            request_id = self._send_unlocked(command)
            if not expect_reply:
                return None
            return self._await_reply(name, request_id, timeout_s)

    def _send_unlocked(self, command: msg.WorkerCommand) -> int:
        request_id, name = next(self._ids), type(command).__name__
        try:
            with self._send_lock:
                self._commands.send(msg.WorkerRequest(request_id, command))
        except (OSError, EOFError) as error:
            raise WorkerError(f"{name}: the worker is gone ({error})") from error
        return request_id

    def _await_reply(self, name: str, request_id: int, timeout_s: float) -> Any:
        deadline = time.monotonic() + timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0 or not self._replies.poll(remaining):
                raise WorkerError(f"{name}: no reply from the worker within {timeout_s} s")
            try:
                reply: msg.WorkerReply = self._replies.recv()
            except (OSError, EOFError) as error:
                raise WorkerError(f"{name}: the worker is gone ({error})") from error
            if reply.request_id != request_id:
                continue  # a late reply to a request that timed out
            if reply.refusal is not None:
                raise reply.refusal.error()
            return reply.result

    def _send_heartbeats(self) -> None:
        """Show the relay this process is alive: advance `service_beats` every heartbeat period."""
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(HEARTBEAT_FIFO_PRIORITY))
        except (OSError, AttributeError) as error:
            log.info("heartbeat thread runs without real-time priority: %s", error)
        beats = self.control.fields["service_beats"]
        while not self._stop_heartbeat.wait(self.heartbeat_period_s):
            beats += np.uint64(1)
