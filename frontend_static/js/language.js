// The clinician's language (issue 16, defect 8): the API answers in SI units, field paths and state names
// for scripts; this layer turns its structured fields (field, value, limit; state, stop reason; event kind
// and details) into sentences in the units and numbering shown on screen, with the next step to take.
// The API's own message stays available (the "details" of a banner, the raw event on demand).

// --- the robot's state in plain words ------------------------------------------------------------------
// Why a stop happened (server/realtime/telemetry.py StopReason), and what to do next.
const STOP_REASONS = {
  watchdog: ["Stopped by the watchdog: the robot lost contact with the console service (no heartbeat), so it stopped the motion.",
    "Next step: attend to the patient, check that the console computer and its network are working, then press Reset robot in the session console and acknowledge the stop before a new run."],
  service_lost: ["Stopped: the robot lost contact with the console service, so it stopped the motion.",
    "Next step: attend to the patient, restart the console service if it is not running, then Reset the robot."],
  late_ticks: ["Stopped: the robot's controller fell behind its timing (late control cycles), so it stopped the motion.",
    "Next step: attend to the patient, close other programs on the console computer, then Reset the robot. Tell the technician if it happens again."],
  limit: ["Stopped at a limit: a movement would have gone past a safe limit of the robot.",
    "Next step: attend to the patient, acknowledge the stop in the session console, and lower the intensity of the prescription before the next run."],
  fall: ["Stopped: a fall was detected.",
    "Next step: attend to the patient first. Then acknowledge the fall in the session console; a new run can start only after that."],
  tracking_error: ["Stopped: the platforms did not follow the planned motion closely enough (something may block them, or the load is too high).",
    "Next step: attend to the patient, check that nothing touches the platforms or rails, then Reset the robot and acknowledge the stop."],
  hal_fault: ["Stopped: a motor drive reported a fault.",
    "Next step: attend to the patient, check the drives' indicator lights and cables, then Reset the robot. Call the technician if it does not clear."],
  internal_error: ["Stopped by an internal software error.",
    "Next step: attend to the patient, then Reset the robot. Call the technician if it happens again."],
  recording_failed: ["Stopped: the session could not be recorded (the data disk is full or failing), so the robot stopped the motion.",
    "Next step: attend to the patient, ask the technician to free space on the console's data disk, then Reset the robot. Nothing recorded before the stop is lost."],
  worker_lost: ["Stopped: the robot's real-time controller ended unexpectedly; the drives stopped on their own, and a new controller runs with the drives off.",
    "Next step: attend to the patient, then Reset the robot before a new run. Tell the technician."],
  daemon_lost: ["Stopped: the robot's control program ended unexpectedly during the run; it was started again with the drives off.",
    "Next step: attend to the patient, then Reset the robot before a new run. Tell the technician."],
  emergency_stop: ["The emergency stop is latched.",
    "Next step: attend to the patient; when it is safe, press Reset robot in the session console, then acknowledge the stop before the next run. Resetting never starts motion."],
};
const CALM_STOPS = new Set(["none", "operator", "completed"]);

// {level: "ok" | "warn" | "bad", label, reason, next, stopReason}: level "bad" for anything that stopped
// the robot abnormally (red), whatever the supervisor's state name is.
export function describeRobot(state) {
  const reasonKey = String(state.stop_reason || "none");
  if (state.estop_latched || state.state === "estop") {
    const [reason, next] = STOP_REASONS.emergency_stop;
    return { level: "bad", label: "E-STOP LATCHED", reason, next, stopReason: "emergency_stop" };
  }
  const abnormal = !CALM_STOPS.has(reasonKey);
  if (state.state === "fault" || (["stopped", "stopping"].includes(state.state) && abnormal)) {
    const [reason, next] = STOP_REASONS[reasonKey] || [`Stopped: ${words(reasonKey)}.`, "Next step: attend to the patient, then Reset the robot in the session console."];
    const label = `${state.state === "fault" ? "FAULT" : "STOPPED"}: ${words(reasonKey).toUpperCase()}`;
    return { level: "bad", label, reason, next, stopReason: reasonKey };
  }
  const labels = { idle: "READY", ready: "READY", running: "MOVING", paused: "PAUSED", stopping: "STOPPING", stopped: "STOPPED" };
  return { level: state.state === "running" || state.state === "paused" ? "warn" : "ok", label: labels[state.state] || String(state.state).toUpperCase(),
    reason: "", next: "", stopReason: reasonKey };
}

export const words = (name) => String(name ?? "").replace(/_/g, " ");
// The motion-cueing algorithm of a prescription (the API's `cueing`), in the clinician's words.
export const CUEING_WORDS = {
  classical: "Classical washout (paper)",
  optimal: "Optimal (planned over the whole prescription)",
};

// --- run outcomes and events -------------------------------------------------------------------------------
export const OUTCOME_WORDS = {
  completed: "completed", stopped: "stopped by the therapist", emergency_stop: "emergency stop", fall: "fall detected",
  fault: "fault", limit_hit: "stopped at a robot limit", interrupted: "interrupted (watchdog or lost connection)",
  running: "running", paused: "paused",
};
// The stops that moved the patient, each acknowledged before the next start (server/reviews/service.py).
const STOP_WORDS = { emergency_stop: "emergency stop", interrupted: "interruption", fault: "fault", fall: "fall", limit_hit: "limit stop" };
export const stopWords = (outcome) => STOP_WORDS[outcome] || words(outcome || "stop");
// The banner after a reset while the last stop waits for its acknowledgement: what to do next, in order.
export function nextStepAfterReset(pending) {
  const what = stopWords(pending.outcome);
  return `The robot is reset. Next step: acknowledge the ${what} of run ${pending.run_id} in the session console `
    + "(below the run controls), then start the next run. The robot starts again only after the acknowledgement.";
}
const EVENT_WORDS = {
  start: "Run started", pause: "Paused", resume: "Resumed", stop: "Stopped by the therapist", reset: "Robot reset",
  emergency_stop: "Emergency stop", fall: "Fall detected", fault: "Fault", limit_hit: "Stopped at a robot limit",
  controlled_stop: "Robot stopped", prescription_completed: "Prescription completed", acknowledged: "Acknowledged by the therapist",
  segment_started: "Segment started", harness_catch: "Harness caught the patient",
  fall_detection_unavailable: "Fall detection off (no force plates on this robot)",
};
// Events a clinician acts on; the rest (state transitions, drive and HAL steps) are engineering detail.
export const CLINICAL_EVENTS = new Set(["start", "pause", "resume", "stop", "reset", "emergency_stop", "fall", "fault",
  "limit_hit", "controlled_stop", "prescription_completed", "acknowledged", "harness_catch", "fall_detection_unavailable"]);
// A detail's unit from its name's SI suffix, and how it is shown (the units of the screen).
const UNIT_SUFFIXES = [
  ["_m_s2", "m/s²", 1, 2], ["_rad_s", "°/s", 180 / Math.PI, 1], ["_rad", "°", 180 / Math.PI, 1], ["_m_s", "mm/s", 1000, 0],
  ["_m2", "cm²", 1e4, 1], ["_mm", "mm", 1, 0], ["_m", "mm", 1000, 0], ["_kg", "kg", 1, 1], ["_n", "N", 1, 0], ["_hz", "Hz", 1, 2],
  ["_us", "µs", 1, 0], ["_s", "s", 1, 2], ["_pct", "%", 1, 0],
];
const HIDDEN_DETAILS = new Set(["tick_from_utc", "prescription_version_id"]);

export function detailWords(details) {
  const parts = [];
  for (const [key, value] of Object.entries(details || {})) {
    if (HIDDEN_DETAILS.has(key) || value === null || value === undefined || value === "") continue;
    const suffix = UNIT_SUFFIXES.find(([end]) => key.endsWith(end));
    if (suffix && typeof value === "number") {
      const [end, unit, scale, digits] = suffix;
      parts.push(`${words(key.slice(0, -end.length))} ${(value * scale).toFixed(digits)} ${unit}`);
    } else if (key === "segment" && Number.isInteger(value)) {
      parts.push(`segment ${value + 1}`);
    } else if (key === "reason" || key === "outcome" || key === "detector" || key === "command" || key === "limit") {
      parts.push(`${words(key)}: ${words(value)}`);
    } else if (typeof value !== "object") {
      parts.push(`${words(key)}: ${value}`);
    }
  }
  return parts.join(", ");
}

// Seconds into the run: the worker's clock minus the run's start on the same clock; else the UTC difference.
export function sessionTime(event, run, startEvent) {
  if (startEvent && Number.isFinite(startEvent.tick_time_s) && Number.isFinite(event.tick_time_s)) {
    return event.tick_time_s - startEvent.tick_time_s;
  }
  if (run && run.started_at) return (new Date(event.utc) - new Date(run.started_at)) / 1000;
  return null;
}

export function eventTitle(event) {
  if (event.kind === "controlled_stop" && event.details && event.details.reason) {
    return `Robot stopped: ${words(event.details.reason)}`;
  }
  return EVENT_WORDS[event.kind] || words(event.kind).replace(/^./, (c) => c.toUpperCase());
}

// --- API errors in the screen's units and numbering -------------------------------------------------------
// Field metadata comes from the input the error belongs to: data-label, data-unit, data-scale (API value ×
// scale = value shown). Segment paths ("segments[0].cue.x") become "Segment 1".
function segmentPrefix(path) {
  const match = /^segments\[(\d+)\]/.exec(path || "");
  return match ? `Segment ${Number(match[1]) + 1}, ` : "";
}
const trim = (value) => String(+Number(value).toPrecision(6));

function shown(value, meta) {
  if (typeof value !== "number" && !(typeof value === "string" && value.trim() !== "" && Number.isFinite(Number(value)))) return null;
  return `${trim(Number(value) * (meta.scale || 1))}${meta.unit ? ` ${meta.unit}` : ""}`;
}

// Bounds of a refusal: pydantic's ctx (gt, ge, lt, le) or the numbers in a domain limit ("must be in [0, 10]").
function bounds(item) {
  const ctx = item.ctx || {};
  const result = {};
  if (ctx.gt !== undefined) result.above = Number(ctx.gt);
  if (ctx.ge !== undefined) result.min = Number(ctx.ge);
  if (ctx.lt !== undefined) result.below = Number(ctx.lt);
  if (ctx.le !== undefined) result.max = Number(ctx.le);
  const limit = String(ctx.limit || item.msg || "");
  const range = /\[\s*(-?[\d.e+-]+)\s*,\s*(-?[\d.e+-]+)\s*\]/.exec(limit);
  if (range) { result.min = Number(range[1]); result.max = Number(range[2]); }
  const atMost = /(?:<=|≤|at most|own limit)\s*(-?[\d.]+(?:e[+-]?\d+)?)/.exec(limit);
  if (atMost && result.max === undefined) result.max = Number(atMost[1]);
  return result;
}

// One refusal, in words: "Segment 1, Amplitude: 50 m/s² is more than the 10 m/s² allowed. Enter 10 m/s² or less."
export function fieldMessage(item, meta = {}) {
  const path = item.path || "";
  const where = `${segmentPrefix(path)}${meta.label || words(path.split(".").pop() || "value")}`;
  if (item.type === "missing") return `${where}: please fill this in.`;
  const b = bounds(item);
  const scale = (v) => shown(v, meta);
  const value = item.input !== undefined ? scale(item.input) : null;
  const low = b.min ?? b.above;
  const high = b.max ?? b.below;
  const number = item.input !== undefined ? Number(item.input) : NaN;
  const lowWords = b.above !== undefined ? `more than ${scale(b.above)}` : low !== undefined ? `at least ${scale(low)}` : "";
  const tooHigh = b.max !== undefined ? number > b.max : b.below !== undefined && number >= b.below;
  const tooLow = b.min !== undefined ? number < b.min : b.above !== undefined && number <= b.above;
  if (Number.isFinite(number) && tooHigh) {
    const most = b.max !== undefined ? `the ${scale(high)} allowed` : `less than ${scale(high)}`;
    return `${where}: ${value} is more than ${most}. Enter ${scale(high)} or less${lowWords ? ` (${lowWords})` : ""}.`;
  }
  if (Number.isFinite(number) && tooLow) {
    return `${where}: ${value} is too low; it must be ${lowWords}${high !== undefined ? ` and at most ${scale(high)}` : ""}.`;
  }
  if (item.type === "literal_error" || item.type === "enum") return `${where}: please choose one of the options.`;
  // Anything else: the API's reason without its field path, in the screen's numbering.
  const reason = String((item.ctx && item.ctx.limit) || item.msg || "").replace(/^[\w.[\]]+ = [^:]*: /, "").replace(/^Value error, /, "");
  return `${where}: ${value ? `${value} — ` : ""}${reason.replace(/segments\[(\d+)\]/g, (m, n) => `segment ${Number(n) + 1}`).replace(/_/g, " ")}.`;
}

// The robot's refusal of a prescription (check_plan): where and which limit, with a suggestion.
const LIMIT_WORDS = {
  rod_reach: "a rod would be stretched beyond its reach", stroke: "a slider would run past the end of its travel",
  base_joint_cone: "a base joint would bend beyond its range", platform_joint_cone: "a platform joint would bend beyond its range",
  tilt: "the platform would tilt beyond its limit", slider_velocity: "a slider would move faster than allowed",
  slider_acceleration: "a slider would accelerate harder than allowed", drive_force: "a drive would have to push harder than allowed",
  singularity: "the robot would pass a pose where it loses stiffness",
};
export function rejectionWords(rejection) {
  if (!rejection) return "";
  const where = Number.isInteger(rejection.segment) ? `In segment ${rejection.segment + 1}, ${Number(rejection.time_s).toFixed(1)} s in: ` : "";
  const what = LIMIT_WORDS[rejection.limit] || words(rejection.limit || rejection.message);
  return `${where}${what}. Lower the amplitude, raise the frequency or shorten the segment, then preview again.`;
}

// 409 refusals of the robot and the service, in words (the API's text is kept for the details).
const CONFLICT_PATTERNS = [
  [/reset: not accepted in state (idle|ready)/i, "Nothing to reset: the robot is already ready."],
  [/reset: not accepted in state (running|paused)/i, "The robot is moving: stop the run before a reset."],
  [/(start|resume): not accepted in state (estop|fault|stopped)/i, "The robot is stopped after a fault or emergency stop: Reset the robot first."],
  [/not accepted in state (\w+)/i, (m) => `Not possible while the robot is ${words(m[1])}.`],
  [/identifier is already used/i, "This record number is already used by another patient: check it, or open that patient."],
  [/(?:occurrence (\d+) of (\d+): )?(robot|patient) already booked from (.+?) \(session (\d+)\); requested (.+?) \(([\w/+-]+) time\)/i,
    (m) => `${m[1] ? `Occurrence ${m[1]} of ${m[2]}: the` : "The"} ${m[3]} is already booked from ${m[4]} (session ${m[5]}); the requested time was ${m[6]} (${m[7]} time).`],
  [/already acknowledged/i, "This stop has already been acknowledged."],
  [/ended with an? (.+?) that is not acknowledged/i, (m) => `The robot's last run ended with ${/^[aeiou]/i.test(m[1]) ? "an" : "a"} ${m[1]}: acknowledge it in the session console before a new run.`],
];
// --- the clinic's clock: dates and times show in the clinic's zone (`clinic_timezone` of GET /health), as the
// week view does, whatever zone the browser's computer is set to; until it is known, the browser's own.
let clinicZone;
export function setClinicZone(zone) {
  try { new Intl.DateTimeFormat(undefined, { timeZone: zone }); clinicZone = zone; } catch (_) { clinicZone = undefined; }
}
export const clinicZoneName = () => clinicZone;
export const clinicDateTime = (when, options = {}) => when.toLocaleString(undefined, { ...options, timeZone: clinicZone });
export const clinicClock = (when, options = {}) => when.toLocaleTimeString(undefined, { ...options, timeZone: clinicZone });

// Times the API quotes in UTC — ISO 8601 with an offset, or "YYYY-MM-DD HH:MM [to HH:MM] UTC" — in this
// clinic's time, as the week view shows them.
const UTC_SPAN = /\b(\d{4}-\d{2}-\d{2})[T ](\d{2}:\d{2})(?: to (\d{2}:\d{2}))? UTC\b/g;
const ISO_TIME = /\b(\d{4}-\d{2}-\d{2})T(\d{2}:\d{2}(?::\d{2}(?:\.\d+)?)?)(Z|[+-]\d{2}:?\d{2})(?![\w:])/g;
const localDateTime = (when) => clinicDateTime(when, { weekday: "short", day: "numeric", month: "short", hour: "2-digit", minute: "2-digit" });
const localClock = (when) => clinicClock(when, { hour: "2-digit", minute: "2-digit" });
export function localTimes(text) {
  return String(text)
    .replace(UTC_SPAN, (match, day, start, end) => {
      const from = new Date(`${day}T${start}:00Z`);
      if (!end) return localDateTime(from);
      const to = new Date(`${day}T${end}:00Z`);
      if (to < from) to.setUTCDate(to.getUTCDate() + 1);
      return `${localDateTime(from)} to ${localClock(to)}`;
    })
    .replace(ISO_TIME, (match) => {
      const when = new Date(match);
      return Number.isNaN(when.getTime()) ? match : localDateTime(when);
    });
}

export function conflictWords(message) {
  const text = localTimes(message || "");
  for (const [pattern, answer] of CONFLICT_PATTERNS) {
    const match = pattern.exec(text);
    if (match) return typeof answer === "function" ? answer(match) : answer;
  }
  return text.replace(/^\w+(Refused|Error): /, "").replace(/segments\[(\d+)\]/g, (m, n) => `segment ${Number(n) + 1}`);
}
