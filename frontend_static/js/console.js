// The live session console: run control with a confirmation before motion, the embedded 3D view,
// live charts from the telemetry WebSocket, fall alerts, worker health, runs, events and exports.
import { get, post, put, query } from "./api.js";
import { LiveChart } from "./charts.js";
import { CLINICAL_EVENTS, OUTCOME_WORDS, clinicClock, describeRobot, detailWords, eventTitle, sessionTime, stopWords, words } from "./language.js";
import { exportControl } from "./exports.js";
import { followPlan } from "./plan.js";
import { metric } from "./pages.js";
import { M_TO_MM, badge, banner, clear, clearErrors, confirmDialog, engineeringOn, fmt, fmtDateTime, h, showError, table } from "./ui.js";

const GRAVITY_M_S2 = 9.80665;
const EXPORT_FORMATS = [["csv", "CSV (zip)"], ["parquet", "Parquet"], ["json", "JSON"], ["c3d", "C3D"]];
// The buttons follow the robot's true state, not only the run records: after an emergency stop or a
// fault, Start stays disabled until the robot is reset (the worker would refuse it anyway). Module scope:
// telemetry frames may arrive while the page is still loading.
const STARTABLE_ROBOT_STATES = ["idle", "ready", "stopped"];
const ACKNOWLEDGEMENT_CHECKS = [
  "I have attended to the patient, who is safe and able to continue (or the session ends here).",
  "I know what caused the stop (see the run's events) and have removed the cause.",
  "The harness, the foot plates and the working area are checked.",
];
const SLIDER_LABELS = Array.from({ length: 12 }, (_, i) => `${i < 6 ? "R" : "L"}${(i % 6) + 1}`);

// Specific force the platform delivers at the feet, stance frame: Rᵀ(a + g e_z) − g e_z, R = Rx·Ry·Rz
// (core.fidelity.platform_specific_force), with a from the stance positions of successive frames.
function platformSpecificForce(angles, acceleration) {
  const [a, b, c] = angles;
  const ca = Math.cos(a), sa = Math.sin(a), cb = Math.cos(b), sb = Math.sin(b), cc = Math.cos(c), sc = Math.sin(c);
  const R = [[cb * cc, -cb * sc, sb], [ca * sc + sa * sb * cc, ca * cc - sa * sb * sc, -sa * cb], [sa * sc - ca * sb * cc, sa * cc + ca * sb * sc, ca * cb]];
  const v = [acceleration[0], acceleration[1], acceleration[2] + GRAVITY_M_S2];
  return [0, 1, 2].map((k) => R[0][k] * v[0] + R[1][k] * v[1] + R[2][k] * v[2] - (k === 2 ? GRAVITY_M_S2 : 0));
}

class AccelerationEstimate {
  // Second differences of 30 Hz frames are noisy; a short exponential average keeps the trend readable.
  constructor() { this.history = []; this.smoothed = [0, 0, 0]; }
  update(t, position) {
    this.history.push([t, position]);
    if (this.history.length > 3) this.history.shift();
    if (this.history.length < 3) return this.smoothed;
    const [[t0, p0], [t1, p1], [t2, p2]] = this.history;
    const dt1 = t1 - t0, dt2 = t2 - t1;
    if (dt1 <= 0 || dt2 <= 0) return this.smoothed;
    const raw = [0, 1, 2].map((k) => ((p2[k] - p1[k]) / dt2 - (p1[k] - p0[k]) / dt1) / ((dt1 + dt2) / 2));
    this.smoothed = this.smoothed.map((s, k) => 0.7 * s + 0.3 * raw[k]);
    return this.smoothed;
  }
}

export async function sessionPage(main, sessionId, cleanup) {
  const booking = await get(`/sessions/${sessionId}`);
  const [patient, prescription] = await Promise.all([
    get(`/patients/${booking.patient_id}`),
    get(`/prescriptions/${booking.prescription_id}/versions/${booking.prescription_version}`),
  ]);
  const prescriptionInfo = await get(`/prescriptions/${booking.prescription_id}`);
  const runState = h("span#run-state.badge.big-state", {}, "—");
  const supervisorState = h("span#supervisor-state", {}, "—");
  const planState = h("span#plan-state", { role: "status" }, "—");
  // Disabled until wired and the runs are known: a button that shows enabled must act when clicked.
  const controls = {
    start: h("button.go#start-button", { type: "button", disabled: true }, "Start"),
    pause: h("button.secondary#pause-button", { type: "button", disabled: true }, "Pause"),
    resume: h("button.secondary#resume-button", { type: "button", disabled: true }, "Resume"),
    stop: h("button.danger#stop-button", { type: "button", disabled: true }, "Stop"),
    reset: h("button.secondary#reset-button", { type: "button", disabled: true, title: "Clears a latched emergency stop or fault; never starts motion" }, "Reset robot"),
  };
  let controlsWired = false;
  const health = h("div.metrics#health");
  const vizHost = h("div#viz-host");
  const vizStatus = h("p.muted#viz-status", { role: "status" }, "3D view: connecting…");
  const chartsHost = h("div.charts#live-charts");
  const chartsTitle = h("h2#charts-title", {}, "Live signals");
  const cameraButtons = h("div.row.camera-presets", { role: "group", "aria-label": "3D view camera" }, h("span.muted", {}, "View from:"),
    [["oblique", "Overview"], ["front", "Front"], ["left", "Left side"], ["right", "Right side"], ["top", "Above"]].map(([preset, label]) =>
      h("button.secondary", { type: "button", onclick: () => post("/viz/camera", { preset }).catch((error) => showError(error, "command")) }, label)));
  const runsHost = h("div#runs");
  const acknowledgePanel = h("div#acknowledge-panel", { hidden: true, role: "alert" });
  const totalS = prescription.content.segments.reduce((s, x) => s + x.duration_s, 0);

  main.append(
    h("h1", {}, `Session console: ${patient.name}`),
    // The run controls come first: with the top bar and two alert banners at 1024×768, Reset robot stays on screen.
    h("div.panel", {},
      h("div.row.run-controls", { role: "group", "aria-label": "Run control" }, controls.start, controls.pause, controls.resume, controls.stop, controls.reset),
      acknowledgePanel, // right under the run controls: the next step after a reset
      h("div.row", {},
        h("div.grow", {},
          h("div", {}, h("strong", {}, "Prescription: "), `${prescriptionInfo.name}, version ${booking.prescription_version} (${prescription.content.segments.length} segment(s), ${fmt(totalS, "s", 0)})`),
          h("div", {}, h("strong", {}, "Booked: "), `${fmtDateTime(booking.start)} on ${booking.robot} · `, badge(booking.status)),
          h("div", {}, h("strong", {}, "Motion plan: "), planState),
          h("div", {}, h("strong", {}, "Robot: "), supervisorState)),
        h("div", {}, h("div.muted", {}, "Run"), runState))),
    h("div.console-grid", {},
      h("section", { "aria-label": "3D view" }, h("h2", {}, "3D view"), vizHost, cameraButtons, vizStatus),
      h("section", { "aria-label": "Worker health" }, h("h2", {}, "Robot and worker health"), health)),
    chartsTitle,
    chartsHost,
    h("h2", {}, "Runs, events, notes and exports"),
    h("button.secondary", { type: "button", onclick: () => post("/viz/live").then(() => { replaySeries = null; resetCharts(liveTitle()); }).catch(showError) }, "3D view: back to live"),
    runsHost);

  // --- live charts -----------------------------------------------------------------------------
  const charts = {
    acceleration: new LiveChart(chartsHost, "Specific force: commanded cue (dashed) vs delivered by the platform", "m/s²", [
      { label: "cue x", color: "#0b4fa8", dash: [8, 5] }, { label: "platform x", color: "#0b4fa8" },
      { label: "cue y", color: "#d1495b", dash: [8, 5] }, { label: "platform y", color: "#d1495b" }]),
    sliders: new LiveChart(chartsHost, "Slider positions", "mm", SLIDER_LABELS.map((label, i) => ({ label, dash: i < 6 ? undefined : [6, 4], width: 1.5, digits: 0 }))),
    forces: new LiveChart(chartsHost, "Drive forces", "N", SLIDER_LABELS.map((label, i) => ({ label, dash: i < 6 ? undefined : [6, 4], width: 1.5, digits: 0 }))),
    cop: new LiveChart(chartsHost, "Centre of pressure, each foot", "mm", [
      { label: "right AP (x)", color: "#e06c00" }, { label: "right ML (y)", color: "#e06c00", dash: [6, 4] },
      { label: "left AP (x)", color: "#00798c" }, { label: "left ML (y)", color: "#00798c", dash: [6, 4] }]),
    loads: new LiveChart(chartsHost, "Harness load and foot-plate vertical forces", "N", [
      { label: "harness", color: "#b00020", width: 3, digits: 0 }, { label: "right plate Fz", color: "#e06c00", digits: 0 }, { label: "left plate Fz", color: "#00798c", digits: 0 }]),
  };
  charts.sliders.box.classList.add("engineering-only");
  charts.forces.box.classList.add("engineering-only");
  const acceleration = new AccelerationEstimate();
  let framesThisSecond = 0;
  let frameRate = 0;
  let lastState = null;
  let activeRun = null; // declared with lastState: telemetry frames may arrive before the runs load
  let pendingReview = null; // a stop of this robot's last run that moved the patient, not yet acknowledged
  // The plan is built and checked ahead (opening this page has it built if it was not): say where it is.
  cleanup.push(followPlan(sessionId, planState, booking.plan));
  const rateTimer = setInterval(() => { frameRate = framesThisSecond; framesThisSecond = 0; renderHealth(); }, 1000);

  function renderHealth() {
    const s = lastState;
    clear(health);
    if (!s) { health.append(metric("Telemetry", "waiting…")); return; }
    const engineering = (el) => { el.classList.add("engineering-only"); return el; };
    const warning = (el) => { el.classList.add("warn"); return el; };
    health.append(
      metric("Robot", describeRobot(s).label, describeRobot(s).level === "bad"),
      metric("Harness load", fmt(s.harness_load_n, "N", 0)),
      ...(s.fall_detection_unavailable ? [warning(metric("Fall detection", "off (no force plates on this robot)"))] : []),
      metric("Emergency stop", s.estop_latched ? "LATCHED" : "clear", s.estop_latched),
      metric("Last stop", words(s.stop_reason)),
      engineering(metric("Drives (HAL)", String(s.hal_state))),
      engineering(metric("Tick compute time", fmt(s.tick_compute_us, "µs", 0), s.tick_compute_us > 800)),
      engineering(metric("Tick lateness", fmt(s.lateness_us, "µs", 0))),
      engineering(metric("Deadline misses", `${s.deadline_misses} ticks`, s.late_streak > 0)),
      engineering(metric("Limit hits", `${s.limit_hits}`, s.limit_hits > 0)),
      engineering(metric("Tracking error", fmt(s.tracking_error_m * M_TO_MM, "mm", 2))),
      engineering(metric("Telemetry rate", `${frameRate} frames/s`, frameRate < 10)),
      engineering(metric("Worker clock", fmt(s.time_s, "s", 1))));
  }

  function plot(t, s, estimator) {
    chartsHost.dataset.plotted = String(Number(chartsHost.dataset.plotted || 0) + 1); // samples drawn since the last reset
    chartsHost.dataset.lastTime = t.toFixed(1);
    const pose = s.stance_pose;
    const delivered = platformSpecificForce(pose.slice(3), estimator.update(t, pose.slice(0, 3)));
    const cue = s.cue_specific_force_m_s2;
    charts.acceleration.push(t, [cue[0], delivered[0], cue[1], delivered[1]]);
    charts.sliders.push(t, s.slider_position_m.map((v) => v * M_TO_MM));
    charts.forces.push(t, s.drive_force_n);
    charts.cop.push(t, [s.plate_cop_m[0][0], s.plate_cop_m[0][1], s.plate_cop_m[1][0], s.plate_cop_m[1][1]].map((v) => v * M_TO_MM));
    charts.loads.push(t, [s.harness_load_n, s.plate_force_z_n[0], s.plate_force_z_n[1]]);
  }
  function resetCharts(title) {
    Object.values(charts).forEach((chart) => chart.reset());
    chartsHost.dataset.plotted = "0";
    chartsTitle.textContent = title;
    chartsHost.dataset.source = replaySeries ? `replay-${replaySeries.run_id}` : "live";
  }
  // The replayed run's samples up to the replay's position, as the 3D view reaches them.
  function followReplay(status) {
    if (!replaySeries) return;
    if (status.mode !== "replay" || status.replay_run_id !== replaySeries.run_id) {
      replaySeries = null;
      resetCharts(liveTitle());
      return;
    }
    const { time_s: times } = replaySeries;
    while (replayShown < times.length && times[replayShown] <= status.replay_position_s + 1e-6) {
      const i = replayShown;
      plot(times[i], Object.fromEntries(Object.keys(replaySeries).filter((k) => Array.isArray(replaySeries[k])).map((k) => [k, replaySeries[k][i]])), replayAcceleration);
      replayShown += 1;
    }
    chartsHost.dataset.replaySamples = String(replayShown);
  }

  function onFrame(frame) {
    if (frame.type === "error") { banner("error", `Robot offline: ${frame.detail}`, { key: "robot" }); return; }
    const s = frame.state;
    if (!s) return;
    const robotStateChanged = !lastState || lastState.state !== s.state;
    lastState = s;
    if (robotStateChanged) { updateControls(); window.dispatchEvent(new CustomEvent("ssp:robot-state", { detail: s })); }
    framesThisSecond += 1;
    chartsHost.dataset.samples = String(Number(chartsHost.dataset.samples || 0) + 1);
    clear(supervisorState).append(badge(s.state), h("span.engineering-only", {}, ` drives ${s.hal_state}`));
    // A replay owns the charts while it plays.
    const t = liveChartTime(s);
    if (!replaySeries) plot(t, s, acceleration);
    for (const event of frame.events || []) {
      if (event.kind === "fall") {
        const into = runStart && Number.isFinite(event.tick_time_s) ? ` ${fmt(event.tick_time_s - runStart.tick_time_s, "s", 1)} into the run` : "";
        banner("fall", `FALL DETECTED${into} (${words(event.detector || "detector")}): the robot stops. Attend to the patient, then acknowledge the fall below before any new run.`, { key: "fall", sticky: true });
      }
    }
    if (frame.events && frame.events.length) refreshRuns();
    if (!lastRender || performance.now() - lastRender > 1000) { lastRender = performance.now(); renderHealth(); }
  }
  let lastRender = 0;
  let chartOrigin = null;
  let chartRunOrigin = null;
  const liveTitle = () => (chartRunOrigin === null ? "Live signals (time since this page opened)" : "Live signals (time into the run)");
  // The live charts' time: into the run (the worker clock minus the run's start event, the clock of the events
  // and banners), else since this page opened; never the worker's uptime. A new origin starts the charts anew.
  function liveChartTime(s) {
    const origin = runStart && Number.isFinite(runStart.tick_time_s) ? runStart.tick_time_s : null;
    if (chartOrigin === null || origin !== chartRunOrigin) {
      chartRunOrigin = origin;
      chartOrigin = origin ?? s.time_s;
      if (!replaySeries) resetCharts(liveTitle());
    }
    return s.time_s - chartOrigin;
  }
  let replaySeries = null; // the replayed run's signals (GET /viz/runs/{id}/series), shown instead of live ones
  let replayShown = 0;
  let replayAcceleration = null;
  let runStart = null; // the active run's start event: times into the run come from the same worker clock

  // --- telemetry WebSocket (reconnects while the page is open) ---------------------------------
  let socket = null;
  let closed = false;
  function connect() {
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    socket = new WebSocket(`${scheme}://${location.host}/api/v1/sessions/${sessionId}/telemetry`);
    socket.onmessage = (message) => onFrame(JSON.parse(message.data));
    socket.onclose = (event) => {
      if (closed) return;
      if (event.code === 1013) banner("error", "Robot offline: no real-time worker is running (records, schedules and exports still work).", { key: "robot", sticky: true });
      setTimeout(connect, 3000);
    };
  }
  connect();

  // --- the 3D view -------------------------------------------------------------------------------
  const viz = await get("/viz").catch(() => ({ available: false, detail: "the 3D view status is unavailable" }));
  if (viz.available) {
    post("/viz/figure", { patient_id: booking.patient_id }).catch(() => null); // the figure takes the patient's height
    post("/viz/controls", { visible: engineeringOn() }).catch(() => null); // viser's panel follows the switch
    vizHost.append(h("iframe.viz-frame#viz-frame", { src: "/api/v1/viz/view/", title: "Live 3D view of the twin robot and the patient", loading: "eager" }));
  } else {
    vizHost.append(h("p.panel", {}, `3D view unavailable: ${viz.detail}`));
  }
  const vizTimer = setInterval(async () => {
    try {
      const st = await get("/viz");
      if (!st.available) return;
      vizStatus.textContent = st.mode === "replay"
        ? `3D view: replay of run ${st.replay_run_id}, ${fmt(st.replay_position_s, "s", 1)} of ${fmt(st.replay_duration_s, "s", 1)}${st.replay_finished ? " (finished)" : ""} · ${st.frames_shown} frames shown`
        : `3D view: live at ${st.rate_hz} Hz · ${st.frames_shown} frames shown`;
      vizStatus.dataset.frames = st.frames_shown;
      vizStatus.dataset.mode = st.mode;
      followReplay(st);
    } catch (_) { /* the banner logic elsewhere reports API trouble */ }
  }, 1000);

  // --- runs, events, exports: each run's panel is built once and updated in place, so a choice made in it
  // (export format, open details, notes being typed) survives the refresh every 3 s -------------------------
  const panels = new Map();
  function updateControls() {
    if (!controlsWired) return; // telemetry may arrive before the listeners are attached
    const robotState = lastState ? lastState.state : null;
    const robotBlocks = robotState !== null && !STARTABLE_ROBOT_STATES.includes(robotState);
    controls.start.disabled = Boolean(activeRun) || robotBlocks || Boolean(pendingReview);
    controls.start.title = pendingReview ? "Acknowledge the last stop first (below)."
      : robotBlocks && !activeRun ? `The robot is ${words(robotState).toUpperCase()}: reset it first.` : "";
    controls.pause.disabled = !activeRun || activeRun.state !== "running";
    controls.resume.disabled = !activeRun || activeRun.state !== "paused";
    controls.stop.disabled = !activeRun;
  }
  function outcomeOf(run) { return run.state === "ended" ? run.outcome || "ended" : run.state; }
  function eventsTable(run, events) {
    const start = events.find((e) => e.kind === "start");
    if (!events.length) return h("p.muted", {}, "No events.");
    return table(["Event", "Time into the run", "Clock time", "What happened"], events.map((e) => {
      const into = sessionTime(e, run, start);
      return h(`tr${CLINICAL_EVENTS.has(e.kind) ? "" : ".engineering-only"}`, { dataset: { kind: e.kind } },
        h("td", {}, h("span.event-kind", {}, eventTitle(e))),
        h("td.num", {}, into === null ? "—" : fmt(into, "s", 1)),
        h("td", {}, clinicClock(new Date(e.utc))),
        h("td", {}, detailWords({ ...(e.detector && e.detector !== "console" ? { detector: e.detector } : {}), ...e.details }) || "—",
          h("details.raw", {}, h("summary", {}, "raw details"), h("pre", {}, JSON.stringify({ ...e, details: e.details }, null, 1)))));
    }));
  }
  function notesForm(run) {
    const areas = Object.fromEntries([["subjective", "S: subjective (what the patient reports)"], ["objective", "O: objective (observed, measured)"],
      ["assessment", "A: assessment"], ["plan", "P: plan (next session)"]].map(([name, label]) => [name, [label, h("textarea", { rows: 2, "data-field": name })]]));
    const status = h("span.muted", { role: "status" });
    const form = h("form.soap", { novalidate: true, onsubmit: async (event) => {
      event.preventDefault();
      try {
        await put(`/runs/${run.id}/notes`, Object.fromEntries(Object.entries(areas).map(([name, [, area]]) => [name, area.value])));
        clearErrors(`notes-${run.id}`);
        status.textContent = `Notes saved at ${clinicClock(new Date())}.`;
      } catch (error) { showError(error, `notes-${run.id}`); }
    } }, Object.values(areas).map(([label, area]) => h("label", {}, label, area)),
    h("div.row", {}, h("button.secondary", { type: "submit" }, `Save notes of run ${run.id}`), status));
    form.load = (notes) => { for (const [name, [, area]] of Object.entries(areas)) if (document.activeElement !== area) area.value = notes[name] || ""; };
    return form;
  }
  function runPanel(run) {
    const format = h("select", { "aria-label": `Export format for run ${run.id}` }, EXPORT_FORMATS.map(([v, t]) => h("option", { value: v }, t)));
    const link = exportControl(`Export run ${run.id} log`, () => `/sessions/${sessionId}/export/jobs?format=${format.value}&run_id=${run.id}`);
    const parts = {
      title: h("h3.grow"), state: h("span"), summary: h("p"), events: h("div"), notes: notesForm(run),
      replay: h("button.secondary", { type: "button", hidden: true, onclick: () => replay(run.id) }, `Replay run ${run.id} in 3D`),
      report: h("a.button", { href: `/api/v1/runs/${run.id}/report.pdf`, target: "_blank", hidden: true }, `PDF report of run ${run.id}`),
      eventsKey: "",
    };
    parts.panel = h("div.panel", { dataset: { runId: run.id } },
      h("div.row", {}, parts.title, parts.state), parts.summary, parts.events,
      h("details.notes", {}, h("summary", {}, "Therapist notes (SOAP)"), parts.notes),
      h("div.row", {}, h("label", {}, "Format ", format), link, parts.replay, parts.report));
    return parts;
  }
  async function updatePanel(parts, run) {
    const [events, review] = await Promise.all([get(`/runs/${run.id}/events`), get(`/runs/${run.id}/review`).catch(() => null)]);
    parts.title.textContent = `Run ${run.id} · started ${fmtDateTime(run.started_at)}`;
    clear(parts.state).append(badge(outcomeOf(run)));
    parts.summary.textContent = `${OUTCOME_WORDS[outcomeOf(run)] || words(outcomeOf(run))} · ${run.sample_count} samples recorded${run.ended_at ? `, ended ${fmtDateTime(run.ended_at)}` : ""}.`;
    const eventsKey = events.map((e) => e.id).join(",");
    if (eventsKey !== parts.eventsKey) { clear(parts.events).append(eventsTable(run, events)); parts.eventsKey = eventsKey; }
    if (review) parts.notes.load(review.notes);
    parts.replay.hidden = run.state !== "ended";
    parts.report.hidden = run.state !== "ended";
    return events;
  }
  function showPending(review) {
    pendingReview = review;
    acknowledgePanel.hidden = !review;
    acknowledgePanel.className = review && review.outcome === "fall" ? "alert-panel fall" : "alert-panel";
    clear(acknowledgePanel);
    if (!review) return;
    const what = OUTCOME_WORDS[review.outcome] || words(review.outcome);
    const stop = stopWords(review.outcome);
    // The button before the explanation: it stays on screen at 1024×768 under the top bar and two banners.
    acknowledgePanel.append(h("h2", {}, `Run ${review.run_id} ended: ${what}`),
      h("button.danger#acknowledge-button", { type: "button", onclick: () => acknowledge(review) }, `Acknowledge the ${stop}`),
      h("p", {}, `The robot ${booking.robot} starts again only after you acknowledge this ${stop}: reset the robot if it is stopped, acknowledge, then start. The acknowledgement is recorded with your name in the run's events.`));
  }
  async function acknowledge(review) {
    const stop = stopWords(review.outcome);
    const ok = await confirmDialog({ title: `Acknowledge the ${stop} of run ${review.run_id}?`,
      body: "Confirm each point. A new run still needs the start checklist.", ok: "Acknowledge", checklist: ACKNOWLEDGEMENT_CHECKS });
    if (!ok) return;
    try {
      await post(`/runs/${review.run_id}/acknowledge`, { note: ACKNOWLEDGEMENT_CHECKS.join(" ") });
      clearErrors("command");
      banner("info", `The ${stop} of run ${review.run_id} is acknowledged.`);
      window.dispatchEvent(new CustomEvent("ssp:acknowledged"));
    } catch (error) { showError(error, "command"); }
    await refreshRuns();
  }
  async function refreshRuns() {
    const [runs, pending] = await Promise.all([get(`/sessions/${sessionId}/runs`), get(`/reviews/pending${query({ robot: booking.robot })}`).catch(() => null)]);
    activeRun = runs.find((r) => r.state === "running" || r.state === "paused") || null;
    const last = runs[runs.length - 1];
    const shown = last ? outcomeOf(last) : "not started";
    runState.className = `badge big-state ${shown}`;
    runState.textContent = words(shown);
    runState.dataset.state = shown;
    showPending(pending);
    updateControls();
    if (!runs.length && !panels.size) clear(runsHost).append(h("p.muted", {}, "No run yet."));
    for (const run of runs) {
      let parts = panels.get(run.id);
      if (!parts) {
        if (!panels.size) clear(runsHost);
        parts = runPanel(run);
        panels.set(run.id, parts);
        runsHost.prepend(parts.panel); // newest first
      }
      const events = await updatePanel(parts, run);
      if (run === activeRun) runStart = events.find((e) => e.kind === "start") || null;
    }
  }
  async function replay(runId) {
    try {
      await post("/viz/replay", { run_id: runId });
      replaySeries = await get(`/viz/runs/${runId}/series?points=4000`);
      replayShown = 0;
      replayAcceleration = new AccelerationEstimate();
      resetCharts(`Signals of run ${runId} (replay, time into the run)`);
      clearErrors("command");
      banner("info", `Replaying run ${runId} in the 3D view and the charts.`);
    } catch (error) { showError(error, "command"); }
  }

  // --- run control -------------------------------------------------------------------------------
  async function command(name) {
    try {
      await post(`/sessions/${sessionId}/${name}`);
    } catch (error) {
      showError(error, "command");
      await refreshRuns();
      return;
    }
    clearErrors("command");
    await refreshRuns();
  }
  controls.start.addEventListener("click", async () => {
    const ok = await confirmDialog({
      title: "Start motion?",
      body: `The platforms will move under ${patient.name}: ${prescriptionInfo.name}, ${fmt(totalS, "s", 0)}. The emergency stop is the red button (key Esc).`,
      ok: "Start motion",
      checklist: ["The patient is in the harness and the harness is attached.", "Both feet are on the foot plates.", "Nobody else is inside the robot's working area."],
    });
    if (!ok) return;
    await post("/viz/live").catch(() => null);
    await command("start");
  });
  controls.pause.addEventListener("click", () => command("pause"));
  controls.resume.addEventListener("click", async () => {
    const ok = await confirmDialog({ title: "Resume motion?", body: "The platforms will move again.", ok: "Resume motion" });
    if (ok) await command("resume");
  });
  controls.stop.addEventListener("click", () => command("stop"));
  controls.reset.addEventListener("click", async () => {
    try {
      await post("/robot/reset");
      clearErrors("command");
      banner("info", "Reset sent: the robot is ready once it shows READY. A reset never starts motion.");
    } catch (error) { showError(error, "command"); }
    await refreshRuns();
  });
  const onEngineering = (event) => { post("/viz/controls", { visible: event.detail }).catch(() => null); };
  window.addEventListener("ssp:engineering", onEngineering);
  const onEstop = () => { setTimeout(refreshRuns, 600); setTimeout(refreshRuns, 2500); };
  window.addEventListener("ssp:estop", onEstop);

  controlsWired = true;
  controls.reset.disabled = false; // the rest follow the runs and the robot's state (updateControls)
  renderHealth();
  await refreshRuns();
  const runsTimer = setInterval(() => refreshRuns().catch(() => null), 3000);
  const onResize = () => Object.values(charts).forEach((c) => c.resize());
  window.addEventListener("resize", onResize);
  cleanup.push(() => {
    closed = true;
    if (socket) socket.close();
    clearInterval(rateTimer); clearInterval(vizTimer); clearInterval(runsTimer);
    window.removeEventListener("ssp:estop", onEstop);
    window.removeEventListener("ssp:engineering", onEngineering);
    window.removeEventListener("resize", onResize);
  });
}
