"""`RobotDaemon`: the daemon's decisions about runs, whatever the transport to the web side.

It owns the run. A start is checked (booking, robot, busy), planned in the planning process, loaded
into the worker and started, and only then recorded, with the run id the daemon chose; a refused start
never touches the running run. Pause, resume, stop, the emergency stop, completion, faults, falls and
the loss of the controlling console or of the worker are decided here and end the run through the one
`end_run`. The recorder thread drains the worker's telemetry and event rings every 20 ms and hands them
to the recorder (server.robotd.recorder: the run's journal, then the database); the console links and
the session-control lease are the link watch's (server.robotd.consoles).

A journal write that fails (disk full, I/O error) is a stop: the run ends with a controlled stop and a
`recording_failed` event, everything it produced stays in memory until the database takes it. Starts are
refused until a probe write succeeds again; `recorder.failure` says why meanwhile (the daemon's status,
hence /health).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from prometheus_client import generate_latest

from server.db import Database
from server.errors import ConflictError, WorkerUnavailableError
from server.observability.metrics import RobotMetrics, WorkerTap
from server.realtime.supervisor import STOP_RAMP_RUNNING
from server.robotd import runs
from server.robotd.consoles import WEB_STALL_TOLERANCE_S, ConsoleLinks
from server.robotd.models import RunOutcome, RunState
from server.robotd.plan_store import PlanStore
from server.robotd.planner import InlinePlanner, Planner
from server.robotd.plans import PlanPreparer
from server.robotd.playback import Playback
from server.robotd.recorder import CHUNK_PERIOD_S, ActiveRun, RunRecorder
from server.robotd.records import event_utc, terminal_outcome_of

if TYPE_CHECKING:
    from core.robot import TwinRobot
    from server.robotd.interfaces import WorkerControl

log = logging.getLogger("ssp_rehab.robotd")

RECORD_PERIOD_S = 0.02  # journal writes at least every 20 ms (the issue asks for 100 ms)
TAIL_S = 10.0  # telemetry after a run ends still belongs to it: the stop that follows, at most this long
TAIL_AFTER_DRIVES_OFF_S = 0.3  # and this long once the drives are off
SHUTDOWN_WAIT_S = 5.0  # for the controlled stop of a run in motion when the daemon is shut down
DAEMON_DETECTOR = "robot daemon"
RESET_WAIT_S = 3.0  # longer than any emergency-stop ramp (at most 2 s, server.realtime.supervisor)
RESET_RETRY_S = 0.02
VERIFIED_LOGIN = "login session"  # the credential of a command whose login the database confirmed
# Why a run ended interrupted when the daemon was stopped with its run still in motion (then "... (SIGTERM)").
DAEMON_STOPPED = "the robot daemon was stopped"
Listener = Callable[[list[dict[str, Any]]], None]


@dataclass
class PendingStart:
    """A start being planned, loaded and armed; a stop or an emergency stop meanwhile cancels it."""

    session_id: int
    estop_generation: int | None  # the worker's emergency-stop request count when the start was asked for
    cancelled: str | None = None  # by what, and when
    armed: bool = False  # the worker accepted `start`: from here a stop stops the run instead
    stopped_by: int | None = None  # who stopped it while it was being recorded


class RobotDaemon:
    def __init__(
        self,
        *,
        robot: str,
        worker: WorkerControl,
        database: Database,
        journal_dir: Path | None,
        planner: Planner | InlinePlanner,
        twin: TwinRobot,
        plan_store: PlanStore,
        chunk_period_s: float = CHUNK_PERIOD_S,
        tail_s: float = TAIL_S,
        web_stall_tolerance_s: float = WEB_STALL_TOLERANCE_S,
        shutdown_wait_s: float = SHUTDOWN_WAIT_S,
    ) -> None:
        self.robot = robot
        self.metrics = RobotMetrics()
        # Counted where the worker's streams are read; the tap forwards everything else to the worker.
        self.worker = cast("WorkerControl", WorkerTap(worker, self.metrics))
        self.database = database
        self.planner = planner
        self.twin = twin
        self.playback: Playback | None = None  # the loaded plan's checked transitions
        self.plans = PlanPreparer(store=plan_store, planner=planner, twin=twin, database=database, robot=robot)
        self.tail_s = tail_s
        self.shutdown_wait_s = shutdown_wait_s
        self.recorder = RunRecorder(robot, database, journal_dir, chunk_period_s)
        self._lock = threading.RLock()
        self.run: ActiveRun | None = None
        self.recent_run_id: int | None = None
        self._starting: PendingStart | None = None
        self._arming: tuple[list[np.ndarray], list[dict[str, Any]]] | None = None
        self.consoles = ConsoleLinks(robot, web_stall_tolerance_s)
        self.listeners: list[Listener] = []
        self.latest_sample: dict[str, Any] | None = None
        self.telemetry_lost = 0
        self._drain_lock = threading.Lock()  # the worker is not replaced in the middle of a drain
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._record_forever, name="robotd-recorder", daemon=True)

    # --- lifecycle --------------------------------------------------------------------------------

    def start(self) -> None:
        self.recorder.start()
        self._thread.start()
        self.plans.start()

    def shutdown(self, reason: str = "the robot daemon shut down") -> None:
        """A run in motion is interrupted with a controlled stop, and its stop recorded, before the end."""
        with self._lock:
            run = self.run
            if run is not None and run.outcome is None:
                self._end(run, RunOutcome.INTERRUPTED, reason)
                with contextlib.suppress(Exception):
                    self.worker.stop()
        deadline = time.monotonic() + self.shutdown_wait_s
        while self.run is not None and self._thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.05)  # the recorder keeps the stop in the run until the drives are off
        self._stop.set()
        self.plans.shutdown()
        self._thread.join(10.0)
        self._record_once()  # what the worker produced last
        with self._lock:
            if self.run is not None:
                self._release(self.run)
        self.recorder.stop()

    # --- commands ---------------------------------------------------------------------------------

    def start_session(
        self, session_id: int, user_id: int, controller: str | None = None, estop_generation: int | None = None
    ) -> int:
        """Start the booking's prescription on this robot; returns the run id. Refusals are 4xx errors.

        `estop_generation` is the worker's count of emergency-stop requests when the start was asked for (read
        here when the caller did not): an emergency stop requested after it, or a stop of this session,
        cancels the start while it loads, and a reset never lets it begin (issue 20, defect 2)."""
        if estop_generation is None:
            estop_generation = self._estop_request()[0]
        self.recorder.refuse_start_while_failing()
        with self.database.session() as session:
            booking, version, patient = runs.startable(session=session, session_id=session_id, robot=self.robot)
            booking_id, patient_id, version_id = booking.id, booking.patient_id, version.id
            content, anthropometrics = version.content, runs.patient_for_worker(patient)
            session.commit()
        with self._lock:
            if self._starting is not None:
                raise ConflictError(f"robot {self.robot!r} is busy starting session {self._starting.session_id}")
            if self.run is not None and self.run.outcome is None:
                raise ConflictError(
                    f"robot {self.robot!r} is busy with run {self.run.run_id} (session {self.run.session_id})"
                )
            self.consoles.take_lease(controller)
            starting = self._starting = PendingStart(session_id, estop_generation)
        log.info("session %d: planning and checking its prescription", session_id)
        try:
            try:
                self._load(content, anthropometrics, starting)
            except Exception as error:
                self._refuse_if_cancelled(starting)
                raise runs.refused(error) from error
            with self._lock:  # a stop or an emergency stop from here on finds the start armed or refused
                self._refuse_if_cancelled(starting)
                if self.run is not None:
                    self._release(self.run)  # the previous run's tail ends here
                self._arming = ([], [])
                try:
                    assert self.playback is not None
                    self.playback.start(self.worker, estop_generation)
                except Exception as error:
                    self._arming = None
                    self._refuse_if_cancelled(starting)
                    raise runs.refused(error) from error
                starting.armed = True
            try:
                clock = self.clock()
                run_id = self.recorder.writer.call(
                    lambda s: (
                        runs.record_start(
                            session=s,
                            booking_id=booking_id,
                            robot=self.robot,
                            patient_id=patient_id,
                            version_id=version_id,
                            clock=clock,
                            actor_id=user_id,
                        ).id
                    )
                )
            except Exception as error:
                # Motion without a record of it is not allowed: stop the robot, then report the failure.
                self.worker.stop()
                self._arming = None
                if isinstance(error, ConflictError):
                    raise
                raise WorkerUnavailableError(
                    f"the run could not be recorded ({type(error).__name__}: {error}); the robot was stopped again"
                ) from error
            self._confirm(run_id, session_id, controller, version_id=version_id, started_by_id=user_id)
            with self._lock:
                if starting.stopped_by is not None and self.run is not None and self.run.run_id == run_id:
                    # A stop that came while the start was being recorded: the worker is stopping already.
                    self._end(
                        self.run, RunOutcome.STOPPED, "stopped by the operator", stopped_by_id=starting.stopped_by
                    )
            return run_id
        finally:
            self._starting = None

    def _estop_request(self) -> tuple[int | None, float | None]:
        """(count of emergency-stop requests, UTC of the latest) as the worker's control block holds them."""
        try:
            generation, utc_s = self.worker.estop_request()
        except AttributeError:  # a worker without a request count: the daemon's own cancellation only
            return None, None
        return int(generation), utc_s

    def _cancel_start(self, starting: PendingStart, why: str, utc_s: float | None = None) -> None:
        """Cancel a start still loading: the first reason wins, and the planner's work is abandoned."""
        if starting.cancelled is None:
            at = dt.datetime.fromtimestamp(utc_s, dt.UTC) if utc_s is not None else dt.datetime.now(dt.UTC)
            starting.cancelled = f"{why} at {at:%H:%M:%S} UTC"
            log.warning("session %d: start cancelled by %s", starting.session_id, starting.cancelled)
        if not starting.armed:
            self.planner.cancel()

    def _check_start_against_estop(self) -> None:
        """An emergency stop requested since the start was asked for cancels it (whatever a reset did since)."""
        starting = self._starting
        if starting is None or starting.armed or starting.cancelled is not None or starting.estop_generation is None:
            return
        generation, utc_s = self._estop_request()
        if generation is not None and generation != starting.estop_generation:
            self._cancel_start(starting, "the emergency stop", utc_s)

    def _refuse_if_cancelled(self, starting: PendingStart) -> None:
        self._check_start_against_estop()
        if starting.cancelled is not None:
            raise ConflictError(
                f"start cancelled by {starting.cancelled}: session {starting.session_id} did not start, nothing "
                "moved and no run was recorded; start it again when the patient is ready",
                field="start",
            )

    def _load(self, content: dict[str, Any], patient: dict[str, Any], starting: PendingStart) -> None:
        plan, report = self.plans.obtain(content, patient, lambda: self._refuse_if_cancelled(starting))
        self._refuse_if_cancelled(starting)
        # The worker refuses this load too if an emergency stop was requested since the start (even if reset).
        self.worker.load_plan(plan, report, estop_generation=starting.estop_generation)
        self.playback = Playback(self.twin, plan)

    def _confirm(
        self, run_id: int, session_id: int, controller: str | None, *, version_id: int, started_by_id: int
    ) -> None:
        """The run is recorded: what arrived since `start_motion` belongs to it."""
        journal, failure = self.recorder.open_journal(run_id)
        with self._lock:
            run = ActiveRun(run_id, session_id, controller, journal, version_id=version_id, started_by_id=started_by_id)
            telemetry, events = self._arming or ([], [])
            self._arming = None
            self.run, self.recent_run_id = run, run_id
            if failure is not None:
                self._recording_failed(run, failure)
            self._take(run, np.concatenate(telemetry) if telemetry else None, events)

    def control(
        self, session_id: int, command: runs.RunCommand, user_id: int, credential: str = VERIFIED_LOGIN
    ) -> dict[str, Any] | None:
        """Pause, resume or stop the session's run. Decided, journalled and answered here; the database
        write follows (retried until the database takes it), so that stopping never waits for it. None when
        a stop cancelled this session's start while it was still loading."""
        with self._lock:
            starting = self._starting
            stops_the_start = command == "stop" and starting is not None and starting.session_id == session_id
            if stops_the_start and starting is not None:
                if not starting.armed:
                    self._cancel_start(starting, "the stop")
                    return None
                starting.stopped_by = user_id  # armed but not yet recorded: stop now, record the end after
                try:
                    self.worker.stop()
                except Exception as error:
                    raise runs.refused(error) from error
        if stops_the_start and starting is not None:
            return self._run_of_stopped_start(starting)
        transition = None
        if command != "stop":  # built and checked outside the lock: a stop meanwhile never waits for it
            with self._lock:
                run = self.run if self.run is not None and self.run.session_id == session_id else None
                runs.check_command(run.state if run is not None and run.outcome is None else None, session_id, command)
                playback = self.playback
            assert playback is not None
            try:
                transition = playback.prepare(command, self.worker)
            except Exception as error:
                raise runs.refused(error) from error
        with self._lock:
            run = self.run if self.run is not None and self.run.session_id == session_id else None
            active = run if run is not None and run.outcome is None else None
            next_state = runs.check_command(active.state if active else None, session_id, command)
            assert active is not None
            try:
                if transition is None:
                    self.worker.stop()
                else:
                    assert self.playback is not None
                    self.playback.send(self.worker, transition)
            except Exception as error:
                raise runs.refused(error) from error
            if command == "stop":
                self._end(
                    active, RunOutcome.STOPPED, "stopped by the operator", stopped_by_id=user_id, credential=credential
                )
            else:
                active.state = next_state
                clock, at = self.clock(), dt.datetime.now(dt.UTC)
                self._journal_decision(
                    active, {"decision": command, "user_id": user_id, "credential": credential, "utc": at}, clock
                )
                self.recorder.writer.submit(
                    lambda s: runs.record_command(
                        session=s,
                        run_id=active.run_id,
                        command=command,
                        clock=clock,
                        actor_id=user_id,
                        at=at,
                        credential=credential,
                    ),
                    retry=True,
                )
            return active.record(self.robot)

    def _run_of_stopped_start(self, starting: PendingStart, timeout_s: float = 60.0) -> dict[str, Any] | None:
        """The run a start being recorded when it was stopped became (it ends `stopped`), once recorded."""
        deadline = time.monotonic() + timeout_s
        while self._starting is starting and time.monotonic() < deadline:
            time.sleep(0.01)
        run = self.run
        return run.record(self.robot) if run is not None and run.session_id == starting.session_id else None

    def reset(self, user_id: int) -> None:
        """Clear a latched stop. Pressed while the robot still brakes (an emergency stop's ramp lasts at most
        2 s), it waits for the drives to be off, up to `RESET_WAIT_S`, rather than being refused."""
        deadline = time.monotonic() + RESET_WAIT_S
        while True:
            try:
                self.worker.reset()
                break
            except Exception as error:  # the worker's refusal (e.g. reset while idle) is the client's conflict
                if STOP_RAMP_RUNNING not in str(error) or time.monotonic() >= deadline:
                    raise runs.refused(error) from error
                time.sleep(RESET_RETRY_S)
        clock = self.clock()
        self.recorder.writer.call(
            lambda s: runs.record_robot_command(session=s, user_id=user_id, command="reset", clock=clock)
        )

    def note_emergency_stop(self, user_id: int | None, authenticated: bool, credential: str) -> list[int]:
        """Who asked for the emergency stop the web side already latched; ends the active run."""
        clock = self.clock()
        with self._lock:
            if self._starting is not None and self._starting.estop_generation is None:
                self._cancel_start(self._starting, "the emergency stop")  # a worker without a request count
            self._check_start_against_estop()  # the request count says whether it came after the start
            run_ids = [self.recent_run_id] if self.recent_run_id is not None and self.run is not None else []
            if self.run is not None:
                self._end(self.run, RunOutcome.EMERGENCY_STOP, "emergency stop", stopped_by_id=user_id)
        self.recorder.writer.submit(
            lambda s: runs.record_emergency_stop(
                session=s,
                user_id=user_id,
                authenticated=authenticated,
                credential=credential,
                run_ids=run_ids,
                clock=clock,
            ),
            retry=True,
        )
        return run_ids

    def metrics_text(self) -> str:
        """The robot's metrics in Prometheus text format (web processes append them to their own)."""
        return generate_latest(self.metrics.registry).decode()

    def active_run(self) -> tuple[int, int] | None:
        """(run id, session id) of a run in motion (not in its tail)."""
        run = self.run
        return (run.run_id, run.session_id) if run is not None and run.outcome is None else None

    def clock(self) -> runs.Clock:
        try:
            state = self.worker.latest_state()
        except Exception:
            return runs.NO_CLOCK
        tick, time_s = state.get("tick"), state.get("time_s")
        return (int(tick) if tick is not None else None), (float(time_s) if time_s is not None else None)

    # --- losses -------------------------------------------------------------------------------------

    def link_opened(self, link_id: str, pid: int | None = None, console: str | None = None) -> None:
        with self._lock:
            self.consoles.opened(link_id, pid, console)

    def link_beat(self, link_id: str) -> None:
        self.consoles.beat(link_id)

    def link_closed(self, link_id: str) -> None:
        with self._lock:
            self.consoles.closed(link_id)
            self._check_controller(closed=link_id)

    def _check_controller(self, closed: str | None = None) -> None:
        """The daemon's reaction to a dead or hung console: the run it controls stops (interrupted)."""
        run = self.run
        if run is None or run.outcome is not None or run.controller is None:
            return
        reason = self.consoles.lost(run.controller, closed)
        if reason is None:
            return
        log.warning("run %d: %s; stopping", run.run_id, reason)
        self._end(run, RunOutcome.INTERRUPTED, reason)
        try:
            self.worker.service_lost(reason)  # type: ignore[attr-defined]
        except Exception:  # the watchdog stops it anyway once the beats end
            log.exception("could not tell the worker that the console is gone")

    def worker_lost(self, reason: str, details: dict[str, Any] | None = None) -> None:
        """The worker process died: the drives stopped on their own heartbeat loss; what it left in its
        rings joins the run, a `worker_lost` event records the stop, and the run closes."""
        with contextlib.suppress(Exception):
            self._record_once()  # the dead worker's last records and events
        with self._lock:
            run = self.run
            if run is not None and run.outcome is None:
                event = self._daemon_event("worker_lost", {"what": reason, **(details or {})})
                self._take(run, None, [event])
                self._end(run, RunOutcome.INTERRUPTED, reason)
                self._announce([event])
            if run is not None:
                self._release(run)

    def replace_worker(self, worker: WorkerControl) -> None:
        """A new worker in place of a dead one (the daemon process restarts it)."""
        with self._drain_lock, self._lock:
            self.worker = cast("WorkerControl", WorkerTap(worker, self.metrics))

    # --- recording failures ---------------------------------------------------------------------------

    def _daemon_event(self, kind: str, details: dict[str, Any]) -> dict[str, Any]:
        tick, tick_time_s = self.clock()
        utc = dt.datetime.now(dt.UTC).isoformat()
        return {"kind": kind, "tick": tick, "tick_time_s": tick_time_s, "utc": utc, "detector": DAEMON_DETECTOR,
                "details": details}  # fmt: skip

    def _announce(self, events: list[dict[str, Any]]) -> None:
        for listener in list(self.listeners):
            try:
                listener(events)
            except Exception:
                log.exception("an event listener failed")

    def _recording_failed(self, run: ActiveRun, error: OSError) -> None:
        """The run's journal cannot be written: stop the robot in a controlled way, now. Nothing is lost
        while the daemon lives: the run's records stay in memory until the database takes them."""
        details = self.recorder.note_failure(run, error)
        event = self._daemon_event("recording_failed", details)
        self.recorder.store_events(run.run_id, [event])  # held in the writer's queue until the database takes it
        self._announce([event])
        if run.outcome is None:
            self._end(run, RunOutcome.INTERRUPTED, f"recording failed: [Errno {error.errno}] {error.strerror}")
            try:
                self.worker.recording_failed(details)  # type: ignore[attr-defined]
            except Exception:
                log.exception("run %d: could not ask the worker for the controlled stop; stopping it", run.run_id)
                with contextlib.suppress(Exception):
                    self.worker.stop()

    # --- recording ----------------------------------------------------------------------------------

    def _record_forever(self) -> None:
        while not self._stop.wait(RECORD_PERIOD_S):
            try:
                self._record_once()
            except Exception:
                log.exception("robot daemon recorder: one pass failed")

    def _record_once(self) -> None:
        self._check_start_against_estop()  # abandons a loading start's planning within a pass of the stop
        with self._drain_lock:
            telemetry = self.worker.drain_telemetry()
            events = self.worker.drain_events()
        self.recorder.probe_when_due()
        if telemetry is not None and len(telemetry):
            last = telemetry[-1]
            self.latest_sample = {name: last[name] for name in telemetry.dtype.names or ()}
        self.telemetry_lost = int(getattr(self.worker, "telemetry_lost", 0))
        with self._lock:
            run = self.run
            if self._arming is not None and run is None:
                if telemetry is not None and len(telemetry):
                    self._arming[0].append(np.array(telemetry, copy=True))
                self._arming[1].extend(events)
            elif run is not None:
                self._take(run, telemetry, events)
            elif events:
                self.recorder.store_events(None, events)
            if run is not None:
                self._check_controller()
                if run.tail_deadline is not None and time.monotonic() >= run.tail_deadline:
                    self._release(run)
                else:
                    self.recorder.store_chunk_when_due(run)
        if events:
            self._announce(events)

    def _take(self, run: ActiveRun, telemetry: np.ndarray | None, events: list[dict[str, Any]]) -> None:
        """Recorded (server.robotd.recorder); then what the events decide: a run's end, a shorter tail."""
        failed = self.recorder.take(run, telemetry, events)
        if failed is not None:
            self._recording_failed(run, failed)
        for event in events:
            if event.get("kind") == "drives_disabled" and run.tail_deadline is not None:
                run.tail_deadline = min(run.tail_deadline, time.monotonic() + TAIL_AFTER_DRIVES_OFF_S)
            outcome = terminal_outcome_of(str(event.get("kind")), event.get("details") or {})
            if outcome is not None and run.outcome is None:
                clock = (event.get("tick"), event.get("tick_time_s"))
                self._end(run, RunOutcome(outcome), str(event.get("kind")), at=event_utc(event.get("utc")), clock=clock)

    def _end(
        self,
        run: ActiveRun,
        outcome: RunOutcome,
        reason: str,
        *,
        at: dt.datetime | None = None,
        clock: runs.Clock | None = None,
        stopped_by_id: int | None = None,
        credential: str | None = None,
    ) -> Any:
        """Decide the end of `run` (the first decision wins), journal it, then record it in the database;
        recording goes on for the tail."""
        at = at or dt.datetime.now(dt.UTC)
        clock = clock or self.clock()
        if run.outcome is None:
            run.outcome, run.state, run.ended_at = outcome, RunState.ENDED, at
            run.tail_deadline = time.monotonic() + self.tail_s
            run.stopped_by_id = stopped_by_id
            decision = {"decision": "end", "outcome": outcome.value, "utc": at, "reason": reason}
            self._journal_decision(run, {**decision, "user_id": stopped_by_id, "credential": credential}, clock)
        elif run.stopped_by_id is None:
            run.stopped_by_id = stopped_by_id
        run_id, decided = run.run_id, run.outcome
        return self.recorder.writer.submit(
            lambda s: runs.end_run(
                session=s,
                run_id=run_id,
                outcome=decided,
                at=at,
                reason=reason,
                clock=clock,
                stopped_by_id=stopped_by_id,
                credential=credential,
            ),
            retry=True,
        )

    @staticmethod
    def _journal_decision(run: ActiveRun, decision: dict[str, Any], clock: runs.Clock) -> None:
        """Before the database: a daemon that dies before the database took it leaves it to recovery."""
        if run.journal is None:
            return
        tick, tick_time_s = clock
        try:
            run.journal.append_decision({**decision, "tick": tick, "tick_time_s": tick_time_s})
        except OSError:
            log.exception("run %d: the decision %r could not be journalled", run.run_id, decision.get("decision"))

    def _release(self, run: ActiveRun) -> None:
        """The run's recording is complete (server.robotd.recorder): the robot is free of it."""
        self.recorder.release(run)
        if self.run is run:
            self.run = None
