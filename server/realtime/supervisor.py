"""The safety supervisor: the session state machine and what each state means for the motion.

    IDLE --load--> READY --start--> RUNNING --pause--> PAUSED --resume--> RUNNING
    RUNNING --the plan's last sample--> STOPPED (completed)
    RUNNING/PAUSED --stop, trigger--> STOPPING --at neutral--> STOPPED
    STOPPED --load--> READY        any --emergency stop--> ESTOP        any --HAL fault--> FAULT
    ESTOP/FAULT/STOPPED --reset--> IDLE (drives stay off: a reset never restarts motion)

Each state is played as motion phases: RUNNING = APPROACH (the checked approach to neutral) → CUE (the
checked plan: every segment's cue and return to neutral; after a resume, the checked blend back into it);
PAUSED = CUE (until the checked pause's first sample) → RETURN (the checked pause: standstill, hold,
neutral) → PARKED; STOPPING = DECELERATE → RETURN; ESTOP = DECELERATE (bounded-jerk ramp to standstill
within `estop_ramp_s`) → DISABLED (HAL quick stop and drives off, IEC 60204-1 category 1), latched.
Controlled-stop triggers (watchdog, late ticks, limit hit, fall, tracking error, service lost) move
RUNNING/PAUSED to STOPPING and say why in `stop_reason`.

This class decides; it does no arithmetic on motion and no I/O. `TickPipeline` plays the phases.
"""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any, ClassVar

from core.errors import InvalidValueError, refuse_unknown_fields
from core.plan.config import PlanConfig, PlanConfigError
from server.realtime.telemetry import StopReason, SupervisorState

MOTION_STATES = (SupervisorState.RUNNING, SupervisorState.PAUSED, SupervisorState.STOPPING)


class Phase(enum.IntEnum):
    DISABLED = 0  # drives off
    APPROACH = 1  # bounded-jerk move to neutral before the first cue
    CUE = 2
    RETURN = 3  # bounded-jerk move to neutral
    DECELERATE = 4  # bounded-jerk ramp to standstill
    PARKED = 6  # stand still at neutral until told otherwise


STOP_RAMP_RUNNING = "the stop ramp is still running"  # a reset's refusal while the robot still brakes


class TransitionRefused(RuntimeError):  # noqa: N818 — a refusal, not a malfunction
    """A command that the current state does not accept; names both."""

    def __init__(self, command: str, state: SupervisorState, reason: str = "") -> None:
        self.command, self.state = command, state
        super().__init__(f"{command}: not accepted in state {state.label}" + (f" ({reason})" if reason else ""))


class SupervisorConfigError(PlanConfigError):
    """An invalid safety-supervisor setting."""


@dataclass(frozen=True)
class SupervisorConfig(PlanConfig):
    """Timings and thresholds of the safety functions; all configurable, all validated. The plan's own
    settings (soft start, fade out, returns, margins) come from `core.plan.config.PlanConfig`, so that the
    plan is built and played with the same numbers."""

    estop_ramp_s: float = 0.3  # emergency stop: standstill within this time, then drives off
    controlled_stop_s: float = 0.5  # controlled stops: standstill within this time
    watchdog_s: float = 0.1  # no heartbeat for this long → controlled stop
    late_ticks_to_stop: int = 10  # this many late ticks in a row → controlled stop
    tracking_error_max_m: float = 0.01  # slider command vs measured position

    error: ClassVar[type[InvalidValueError]] = SupervisorConfigError

    def __post_init__(self) -> None:
        super().__post_init__()
        if not isinstance(self.late_ticks_to_stop, int):
            raise SupervisorConfigError("late_ticks_to_stop", self.late_ticks_to_stop, "must be an integer")
        if self.watchdog_s > 1.0:
            raise SupervisorConfigError("watchdog_s", self.watchdog_s, "must be <= 1 s")
        if self.estop_ramp_s > 2.0:
            raise SupervisorConfigError("estop_ramp_s", self.estop_ramp_s, "must be <= 2 s")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> SupervisorConfig:
        refuse_unknown_fields(cls, data, SupervisorConfigError, "supervisor setting")
        return cls(**data)


EventSink = Callable[[str, dict[str, Any]], None]


class Supervisor:
    """The state machine. Commands raise `TransitionRefused` when the state does not allow them;
    triggers never raise (a running session reacts to faults, it does not throw)."""

    def __init__(self, config: SupervisorConfig, emit: EventSink) -> None:
        self.config = config
        self._emit = emit
        self.state = SupervisorState.IDLE
        self.phase = Phase.DISABLED
        self.phase_changed = False  # set on every phase change; the pipeline clears it once it has set up the phase
        self.stop_reason = StopReason.NONE
        self.estop_latched = False
        self.has_prescription = False
        self.heartbeat_age_s = 0.0
        self._watchdog_reported = False
        self.late_streak = 0

    # --- commands ---------------------------------------------------------------------------------

    def load(self) -> None:
        self.require("load", SupervisorState.IDLE, SupervisorState.READY, SupervisorState.STOPPED)
        self.has_prescription = True
        self._enter(SupervisorState.READY, Phase.DISABLED)

    def start(self) -> None:
        self.require("start", SupervisorState.READY)
        self._require_heartbeat("start")
        self.stop_reason = StopReason.NONE
        self._enter(SupervisorState.RUNNING, Phase.APPROACH)

    def pause(self) -> None:
        """Paused: the plan plays on to the sample where its checked pause begins (`pause_begins`)."""
        self.require("pause", SupervisorState.RUNNING)
        self._enter(SupervisorState.PAUSED, Phase.CUE)

    def pause_begins(self) -> None:
        """The checked pause has taken over from the plan: to standstill, hold, back to neutral."""
        if self.state is SupervisorState.PAUSED:
            self._set_phase(Phase.RETURN)

    def resume(self) -> None:
        self.require("resume", SupervisorState.PAUSED)
        self._require_heartbeat("resume")
        if self.phase is not Phase.PARKED:
            raise TransitionRefused("resume", self.state, "the platform is still returning to neutral")
        self._enter(SupervisorState.RUNNING, Phase.CUE)

    def stop(self) -> None:
        self.require("stop", SupervisorState.RUNNING, SupervisorState.PAUSED, SupervisorState.STOPPING)
        if self.state is not SupervisorState.STOPPING:
            self.controlled_stop(StopReason.OPERATOR, {})

    def emergency_stop(self, details: dict[str, Any]) -> None:
        """From every state. Motion ramps to standstill (if there is any), then the drives go off."""
        if self.state is SupervisorState.ESTOP:
            return
        moving = self.phase is not Phase.DISABLED
        self.stop_reason = StopReason.EMERGENCY_STOP
        self.estop_latched = True
        self._emit("emergency_stop", {"from_state": self.state.label, **details})
        self._enter(SupervisorState.ESTOP, Phase.DECELERATE if moving else Phase.DISABLED)

    def reset(self) -> None:
        """Clear a latched emergency stop or fault, or leave STOPPED; always to IDLE with drives off."""
        self.require("reset", SupervisorState.ESTOP, SupervisorState.FAULT, SupervisorState.STOPPED)
        if self.phase is not Phase.DISABLED:
            raise TransitionRefused("reset", self.state, STOP_RAMP_RUNNING)
        self.estop_latched = False
        self.has_prescription = False
        self._enter(SupervisorState.IDLE, Phase.DISABLED)

    # --- triggers ---------------------------------------------------------------------------------

    def controlled_stop(self, reason: StopReason, details: dict[str, Any]) -> None:
        """Stop the session's motion: decelerate, then return to neutral. Ignored when not moving."""
        if self.state not in (SupervisorState.RUNNING, SupervisorState.PAUSED):
            return
        self.stop_reason = reason
        self._emit("controlled_stop", {"reason": reason.name.lower(), "from_state": self.state.label, **details})
        self._enter(SupervisorState.STOPPING, Phase.DECELERATE)

    def fault(self, reason: StopReason, details: dict[str, Any]) -> None:
        """The HAL faulted (or the motion could not be made safe): the drives have quick-stopped."""
        if self.state in (SupervisorState.FAULT, SupervisorState.ESTOP):
            return
        self.stop_reason = reason
        self._emit("fault", {"reason": reason.name.lower(), "from_state": self.state.label, **details})
        self._enter(SupervisorState.FAULT, Phase.DISABLED)

    def heartbeat(self) -> None:
        self.heartbeat_age_s = 0.0
        if self._watchdog_reported:
            self._emit("heartbeat_restored", {})
            self._watchdog_reported = False

    def advance_watchdog(self, elapsed_s: float) -> None:
        """Age the heartbeat by one tick; past `watchdog_s` a moving session stops."""
        self.heartbeat_age_s += elapsed_s
        # The tolerance absorbs the rounding of summed periods: the stop comes on the first tick *past* 100 ms.
        if self.heartbeat_age_s > self.config.watchdog_s + 1e-9 and not self._watchdog_reported:
            self._watchdog_reported = True
            details = {"heartbeat_age_s": round(self.heartbeat_age_s, 4), "watchdog_s": self.config.watchdog_s}
            if self.state in (SupervisorState.RUNNING, SupervisorState.PAUSED):
                self.controlled_stop(StopReason.WATCHDOG, details)
            else:
                self._emit("heartbeat_lost", details)

    def tick_lateness(self, late: bool) -> None:
        """Count consecutive late ticks; too many in a row stop a moving session."""
        self.late_streak = self.late_streak + 1 if late else 0
        if self.late_streak == self.config.late_ticks_to_stop:
            self.controlled_stop(StopReason.LATE_TICKS, {"late_ticks_in_a_row": self.late_streak})

    # --- phase progress (reported by the pipeline) ------------------------------------------------

    def phase_finished(self) -> None:
        """The current phase's ramp or hold is over; move on."""
        state, phase = self.state, self.phase
        if state is SupervisorState.RUNNING and phase in (Phase.APPROACH, Phase.RETURN):
            self._set_phase(Phase.CUE)  # the first segment, or the next one
        elif state is SupervisorState.PAUSED and phase is Phase.RETURN:
            self._emit("paused_at_neutral", {})
            self._set_phase(Phase.PARKED)
        elif state is SupervisorState.STOPPING:
            if phase is Phase.DECELERATE:
                self._set_phase(Phase.RETURN)
            else:
                self._enter(SupervisorState.STOPPED, Phase.DISABLED)
        elif state is SupervisorState.ESTOP and phase is Phase.DECELERATE:
            self._emit("standstill", {"reason": "emergency_stop"})
            self._set_phase(Phase.DISABLED)

    def plan_finished(self) -> None:
        """The plan's last sample (neutral, at rest, after the last segment's return) is out: drives off."""
        if self.state is not SupervisorState.RUNNING:
            return
        self.stop_reason = StopReason.COMPLETED
        self._emit("prescription_completed", {})
        self._enter(SupervisorState.STOPPED, Phase.DISABLED)

    # --- internals --------------------------------------------------------------------------------

    @property
    def drives_enabled(self) -> bool:
        return self.phase is not Phase.DISABLED

    def require(self, command: str, *states: SupervisorState) -> None:
        if self.state not in states:
            raise TransitionRefused(command, self.state, f"accepted in {', '.join(s.label for s in states)}")

    def _require_heartbeat(self, command: str) -> None:
        if self.heartbeat_age_s > self.config.watchdog_s:
            raise TransitionRefused(
                command, self.state, f"no heartbeat from the service for {self.heartbeat_age_s:.3f} s"
            )

    def _enter(self, state: SupervisorState, phase: Phase) -> None:
        previous = self.state
        self.state = state
        self._set_phase(phase)
        if state is not previous:
            self._emit(
                "state", {"from": previous.label, "to": state.label, "stop_reason": self.stop_reason.name.lower()}
            )

    def _set_phase(self, phase: Phase) -> None:
        self.phase = phase
        self.phase_changed = True
