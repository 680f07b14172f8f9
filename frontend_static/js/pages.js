// Login, patients, patient profile, prescription editor, schedule week view and session history.
import { ApiError, del, get, patch, post, put, query } from "./api.js";
import { protocolByKey } from "./protocols.js";
import { staticChart } from "./charts.js";
import { CUEING_WORDS, OUTCOME_WORDS, rejectionWords, words } from "./language.js";
import {
  M_TO_MM, RAD_TO_DEG, badge, banner, clear, clearErrors, confirmDialog, field, fmt, fmtDateTime, fmtTime, h,
  showError, showFieldErrors, table,
} from "./ui.js";

// To a page; the same page again is rendered afresh (a saved record shows its new state, e.g. its version).
const go = (hash) => {
  if (location.hash === hash) window.dispatchEvent(new HashChangeEvent("hashchange"));
  else location.hash = hash;
};
// A refused form: each refusal beside its field, in the field's units; the rest in one banner.
function showRefusal(form, error) {
  const unplaced = error.status === 422 ? showFieldErrors(form, error.fieldItems) : [];
  if (error.status !== 422) showError(error, "form");
  else if (unplaced.length) banner("error", `Please check: ${unplaced.join(" ")}`, { key: "form" });
  else clearErrors("form");
}

// --- login ---------------------------------------------------------------------------------------
export function loginPage(main, { onLogin }) {
  const username = h("input", { name: "username", autocomplete: "username", required: true, "data-field": "username" });
  const password = h("input", { name: "password", type: "password", autocomplete: "current-password", required: true, "data-field": "password" });
  const form = h("form.panel.login", {
    onsubmit: async (event) => {
      event.preventDefault();
      try {
        const result = await post("/auth/login", { username: username.value, password: password.value });
        clearErrors("login");
        onLogin(result.user);
      } catch (error) {
        if (error.status === 422) showFieldErrors(form, error.fieldErrors);
        else showError(error, "login");
      }
    },
  },
  h("h1", {}, "Log in"),
  field("Username", username),
  field("Password", password),
  h("button.primary", { type: "submit" }, "Log in"));
  main.append(form);
  username.focus();
}

// --- patients ------------------------------------------------------------------------------------
const SEXES = ["female", "male", "other", "unknown"];
const SIDES = ["none", "left", "right", "both"];

export async function patientsPage(main) {
  const search = h("input", { type: "search", placeholder: "Name or record number", "aria-label": "Search patients" });
  const archived = h("input", { type: "checkbox", id: "show-archived" });
  const results = h("div");
  const load = async () => {
    const patients = await get(`/patients${query({ search: search.value.trim(), include_archived: archived.checked || undefined })}`);
    clear(results).append(patients.length ? table(
      ["Record number", "Name", "Date of birth", "Diagnosis", ""],
      patients.map((p) => h("tr.clickable", {},
        h("td", {}, p.identifier), h("td", {}, p.name, p.archived_at ? h("span.badge.cancelled", {}, " archived") : null),
        h("td", {}, p.date_of_birth), h("td", {}, p.diagnosis || "—"),
        h("td", {}, h("a.button", { href: `#/patients/${p.id}` }, "Open profile")))),
    ) : h("p.muted", {}, "No patient matches."));
  };
  let timer = null;
  search.addEventListener("input", () => { clearTimeout(timer); timer = setTimeout(() => load().catch(showError), 250); });
  archived.addEventListener("change", () => load().catch(showError));
  main.append(h("h1", {}, "Patients"),
    h("div.row", {}, h("div.grow", {}, field("Search (accents and case do not matter)", search)),
      h("label.inline-check", { for: "show-archived" }, archived, " Show archived records"),
      h("button.primary", { type: "button", onclick: () => go("#/patients/new") }, "New patient")),
    results);
  search.focus();
  await load();
}

export function newPatientPage(main) { return patientFormPage(main, null); }

// Create a patient, or edit one (`patient` given). Sex has no default: the clinician chooses it.
export function patientFormPage(main, patient) {
  const input = (name, attrs = {}) => h("input", { name, "data-field": name, ...attrs });
  const select = (name, options, { placeholder } = {}) => h("select", { name, "data-field": name },
    placeholder ? h("option", { value: "", disabled: true, selected: true }, placeholder) : null,
    options.map((o) => h("option", { value: o }, words(o))));
  const f = {
    identifier: input("identifier", { required: true }),
    name: input("name", { required: true }),
    date_of_birth: input("date_of_birth", { type: "date", required: true }),
    sex: select("sex", SEXES, { placeholder: "Choose…" }),
    // Entered in cm; the API takes metres (data-scale: API value × 100 = value shown, for its messages).
    height_m: input("height_m", { type: "number", step: "1", min: "50", max: "250", required: true, "data-scale": "100" }),
    body_mass_kg: input("body_mass_kg", { type: "number", step: "0.1", min: "10", max: "250", required: true }),
    diagnosis: input("diagnosis"),
    affected_side: select("affected_side", SIDES),
    contraindications: h("textarea", { name: "contraindications", "data-field": "contraindications", rows: 2 }),
    notes: h("textarea", { name: "notes", "data-field": "notes", rows: 3 }),
  };
  if (patient) {
    for (const name of ["identifier", "name", "date_of_birth", "sex", "body_mass_kg", "diagnosis", "affected_side", "contraindications", "notes"]) f[name].value = patient[name];
    f.height_m.value = Math.round(patient.height_m * 100);
  }
  const form = h("form.panel", {
    novalidate: true,
    onsubmit: async (event) => {
      event.preventDefault();
      const body = {
        identifier: f.identifier.value, name: f.name.value, date_of_birth: f.date_of_birth.value, sex: f.sex.value || undefined,
        height_m: f.height_m.value === "" ? undefined : Number(f.height_m.value) / 100,
        body_mass_kg: f.body_mass_kg.value === "" ? undefined : Number(f.body_mass_kg.value), diagnosis: f.diagnosis.value,
        affected_side: f.affected_side.value, contraindications: f.contraindications.value, notes: f.notes.value,
      };
      try {
        const saved = patient ? await patch(`/patients/${patient.id}`, body, { version: patient.version }) : await post("/patients", body);
        clearErrors("form");
        banner("info", `Patient ${saved.name} ${patient ? "saved" : "created"}.`);
        go(`#/patients/${saved.id}`);
      } catch (error) {
        showRefusal(form, error);
      }
    },
  },
  h("div.form-grid", {},
    field("Record number", f.identifier), field("Name", f.name), field("Date of birth", f.date_of_birth), field("Sex", f.sex),
    field("Height", f.height_m, { unit: "cm" }), field("Body mass", f.body_mass_kg, { unit: "kg" }),
    field("Diagnosis", f.diagnosis), field("Affected side", f.affected_side)),
  field("Contraindications", f.contraindications), field("Notes", f.notes),
  h("div.row", {}, h("button.primary", { type: "submit" }, patient ? "Save patient" : "Create patient"),
    h("a.button", { href: patient ? `#/patients/${patient.id}` : "#/patients" }, "Cancel")));
  main.append(h("h1", {}, patient ? `Edit patient: ${patient.name}` : "New patient"), form);
  f.identifier.focus();
}

export async function editPatientPage(main, patientId) {
  patientFormPage(main, await get(`/patients/${patientId}`));
}

export async function patientPage(main, patientId) {
  const [patient, prescriptions, bookings, trend] = await Promise.all([
    get(`/patients/${patientId}`),
    get(`/prescriptions${query({ patient_id: patientId })}`),
    get(`/sessions${query({ patient_id: patientId, limit: 200 })}`),
    get(`/patients/${patientId}/trends`).catch(() => null),
  ]);
  main.append(
    h("h1", {}, `${patient.name} `, h("span.muted", {}, `(${patient.identifier})`)),
    h("div.panel.metrics", {},
      metric("Date of birth", patient.date_of_birth), metric("Sex", patient.sex),
      metric("Height", fmt(patient.height_m * 100, "cm", 0)), metric("Body mass", fmt(patient.body_mass_kg, "kg", 1)),
      metric("Diagnosis", patient.diagnosis || "—"), metric("Affected side", patient.affected_side)),
    patient.archived_at ? h("p.verdict.bad", { role: "status" }, `Archived on ${fmtDateTime(patient.archived_at)}: the record is kept, but it is left out of the lists.`) : "",
    h("p", {}, h("strong", {}, "Contraindications: "), patient.contraindications || "none recorded"),
    h("div.panel#patient-notes", {}, h("strong", {}, "Notes: "), patient.notes ? h("span.pre-line", {}, patient.notes) : h("span.muted", {}, "none")),
    h("div.row", {}, h("a.button", { href: `#/patients/${patientId}/edit` }, "Edit patient"),
      h("button.secondary", { type: "button", onclick: () => archivePatient(patient) }, patient.archived_at ? "Restore from archive" : "Archive patient"),
      progressReportLink(patientId),
      h("a.button", { href: `#/protocols?patient=${patientId}` }, "Start from a protocol")),
    careTeamPanel(patientId),
    h("h2", {}, "Prescriptions"),
    h("div.row", {}, h("a.button.primary", { href: `#/prescriptions/new?patient=${patientId}` }, "New prescription"),
      h("a.button", { href: `#/schedule?patient=${patientId}` }, "Schedule a session")),
    prescriptions.length ? table(["Name", "Version", "Segments", "Total duration", "Motion cueing", ""], prescriptions.map((p) => h("tr", {},
      h("td", {}, p.name), h("td.num", {}, `v${p.latest_version}`), h("td.num", {}, p.current.content.segments.length),
      h("td.num", {}, fmt(p.current.content.segments.reduce((s, x) => s + x.duration_s, 0), "s", 0)),
      h("td", {}, CUEING_WORDS[p.current.content.cueing || "classical"]),
      h("td", {}, h("a.button", { href: `#/prescriptions/${p.id}` }, "Edit / preview"))))) : h("p.muted", {}, "No prescription yet."),
  );
  const runs = trend ? trend.runs : [];
  const falls = runs.reduce((sum, run) => sum + run.falls, 0);
  const faulted = runs.filter((run) => run.status === "faulted").length;
  main.append(h("h2", {}, "Balance trend"),
    h("p", {}, `${runs.length} recorded run(s), ${falls} fall(s), ${faulted} faulted run(s).`));
  if (runs.some((run) => run.sway)) {
    trendCharts(main, trend);
    main.append(h("p.muted", {}, `Prieto et al. (1996) measures of the centre of pressure, low-pass filtered at `
      + `${trend.method.filter.cutoff_hz} Hz. Red points: falls and faulted runs. No normative band is drawn: `
      + "none has a verified published source for training on moving platforms."));
  } else if (runs.length) {
    const minimum = trend.method.min_window_s;
    main.append(h("p.muted#balance-not-measured", {}, `No run long enough for sway measures yet: they need at least ${minimum} s `
      + "of a run in motion with the feet on the plates."));
  } else {
    main.append(h("p.muted", {}, "No run with force-plate data yet: the trend appears after the first session."));
  }
  main.append(h("h2", {}, "Session history"), await sessionsTable(bookings.slice().reverse()));
}

// Who may see and change this record besides the admins (docs/service.md): members and admins remove,
// admins (who see the accounts) add a colleague for cover or a handover.
function careTeamPanel(patientId) {
  const panel = h("div.panel#care-team", { "aria-live": "polite" }, h("strong", {}, "Care team: "), "…");
  const load = async () => {
    const [members, accounts] = await Promise.all([
      get(`/patients/${patientId}/care-team`),
      get("/users").catch(() => null), // admins only
    ]);
    const remove = async (member) => {
      const ok = await confirmDialog({ title: `Remove ${member.full_name || member.username} from the care team?`,
        body: "They will no longer see or change this patient's record, prescriptions, sessions and runs.", ok: "Remove" });
      if (!ok) return;
      try { await del(`/patients/${patientId}/care-team/${member.user_id}`); await load(); } catch (error) { showError(error, "care-team"); }
    };
    const memberIds = new Set(members.map((m) => m.user_id));
    const candidates = (accounts || []).filter((a) => a.is_active && a.role === "therapist" && !memberIds.has(a.id));
    const choice = h("select", { "aria-label": "Clinician to add to the care team" },
      candidates.map((a) => h("option", { value: String(a.id) }, a.full_name || a.username)));
    const add = async () => {
      try { await post(`/patients/${patientId}/care-team`, { user_id: Number(choice.value) }); clearErrors("care-team"); await load(); } catch (error) { showError(error, "care-team"); }
    };
    panel.replaceChildren(h("strong", {}, "Care team: "),
      members.length ? members.map((m) => h("span.member", {}, m.full_name || m.username, " ",
        h("button.secondary", { type: "button", onclick: () => remove(m), "aria-label": `Remove ${m.full_name || m.username}` }, "×"), " "))
        : h("span.muted", {}, "nobody yet (admins only)"),
      accounts === null ? h("span.muted", {}, " An admin adds a colleague for cover or a handover.")
        : candidates.length ? h("span.row", {}, choice, h("button", { type: "button", onclick: add }, "Add to care team")) : "");
  };
  load().catch((error) => showError(error, "care-team"));
  return panel;
}

// The progress report over a period (both dates optional, inclusive).
function progressReportLink(patientId) {
  const from = h("input", { type: "date", "aria-label": "Progress report from" });
  const to = h("input", { type: "date", "aria-label": "Progress report to" });
  const link = h("a.button", { target: "_blank" }, "Progress report (PDF)");
  const update = () => { link.href = `/api/v1/patients/${patientId}/progress.pdf${query({ from: from.value, to: to.value })}`; };
  from.addEventListener("change", update);
  to.addEventListener("change", update);
  update();
  return h("span.row.progress-report", {}, link, h("label", {}, "from ", from), h("label", {}, "to ", to));
}

async function archivePatient(patient) {
  const archiving = !patient.archived_at;
  const ok = await confirmDialog({
    title: archiving ? `Archive ${patient.name}?` : `Restore ${patient.name}?`,
    body: archiving ? "The record, its prescriptions and runs are kept; the patient leaves the lists and the booking form." : "The patient appears in the lists again.",
    ok: archiving ? "Archive" : "Restore",
  });
  if (!ok) return;
  try {
    await patch(`/patients/${patient.id}`, { archived: archiving }, { version: patient.version });
    clearErrors("form");
    banner("info", archiving ? `${patient.name} archived.` : `${patient.name} restored.`);
    go(`#/patients/${patient.id}`);
  } catch (error) { showError(error, "form"); }
}

// Balance trends by date (GET /patients/{id}/trends): one chart per series with its one unit on the y-axis;
// falls and faulted runs are drawn as red points over the line.
function trendCharts(host, trends) {
  const charts = h("div.charts#balance-trend");
  host.append(charts);
  for (const series of trends.series) {
    if (!series.points.length) continue;
    const x = series.points.map((p) => Date.parse(p.started_at) / 1000);
    const values = series.points.map((p) => p.value);
    const marked = series.points.map((p) => (p.status === "ok" ? null : p.value));
    staticChart(charts, series.label, series.unit, x, [values, marked],
      [{ label: series.label, points: 6, spanGaps: true }, { label: "fall or faulted run", color: "#b00020", points: 10, pointsOnly: true }],
      { xLabel: "date", xTime: true, yRange: (u, min, max) => [0, max > 0 ? max * 1.15 : 1] });
  }
}

function metric(label, value, bad = false) {
  return h(`div.metric${bad ? ".bad" : ""}`, {}, h("div.label", {}, label), h("div.value", {}, value));
}
export { metric };

// The run's PDF report (server/reports), once it has ended.
function reportLink(run) {
  if (!run || run.state !== "ended") return null;
  return h("a.button", { href: `/api/v1/runs/${run.id}/report.pdf`, target: "_blank", title: `Outcome: ${OUTCOME_WORDS[run.outcome] || words(run.outcome)}` }, `PDF report (run ${run.id})`);
}

async function sessionsTable(bookings) {
  if (!bookings.length) return h("p.muted", {}, "No session yet.");
  const rows = await Promise.all(bookings.map(async (b) => {
    const runs = await get(`/sessions/${b.id}/runs`);
    const last = runs[runs.length - 1];
    return h("tr", {},
      h("td", {}, fmtDateTime(b.start)), h("td", {}, badge(b.status)), h("td.num", {}, runs.length),
      h("td", {}, last ? badge(last.outcome || last.state) : "—"),
      h("td", {}, h("a.button", { href: `#/session/${b.id}` }, "Open"), " ", reportLink(last)));
  }));
  return table(["Booked for", "Booking", "Runs", "Last outcome", ""], rows);
}

// --- prescription editor -------------------------------------------------------------------------
// Every cue kind of core.cues has a form. Fields: [name, label, unit shown, factor from the API's SI value
// to the unit shown, default (null: optional, left out when empty)]. "amplitude", "initial" and "final"
// take the axis's unit (m/s² for x, y, z; °/s for roll, pitch, yaw).
const AXES = ["x", "y", "z", "roll", "pitch", "yaw"];
const AXIS_WORDS = { x: "x (forward–back)", y: "y (side to side)", z: "z (up–down)", roll: "roll", pitch: "pitch", yaw: "yaw" };
const ROTATION = new Set(["roll", "pitch", "yaw"]);
const AXIS_VALUES = new Set(["amplitude", "initial", "final"]);
const CUE_FIELDS = {
  sine: [["amplitude", "Amplitude", null, null, 0.5], ["frequency_hz", "Frequency", "Hz", 1, 0.5]],
  square_wave: [["amplitude", "Amplitude", null, null, 0.5], ["period_s", "Period", "s", 1, 4], ["duty", "Duty cycle", "fraction", 1, 0.5]],
  step: [["initial", "Level before the step", null, null, 0], ["final", "Level after the step", null, null, 0.5],
    ["step_time_s", "Step at", "s", 1, 2], ["end_time_s", "Back to the first level at (optional)", "s", 1, null]],
  multisine: [],
  perturbations: [["translation_m_s2", "Translation pulse", "m/s²", 1, 1.0], ["tilt_rate_rad_s", "Tilt rate pulse", "°/s", RAD_TO_DEG, 0],
    ["pulse_duration_s", "Pulse duration", "s", 1, 0.5], ["interval_min_s", "Shortest interval", "s", 1, 3], ["interval_max_s", "Longest interval", "s", 1, 8]],
  gait: [["cadence_steps_per_min", "Cadence", "steps/min", 1, 90], ["lateral_amplitude_m_s2", "Lateral amplitude", "m/s²", 1, 0.5],
    ["forward_amplitude_m_s2", "Forward amplitude", "m/s²", 1, 0.3], ["vertical_amplitude_m_s2", "Vertical amplitude", "m/s²", 1, 0]],
  csv_replay: [],
};
const KIND_WORDS = { sine: "sine", square_wave: "square wave", step: "step", multisine: "sum of sines (multisine)",
  perturbations: "random perturbations", gait: "gait-like", csv_replay: "recorded cue (CSV upload)" };
const AXIS_KINDS = new Set(["sine", "square_wave", "step"]);
const axisUnit = (axis) => (ROTATION.has(axis) ? ["rad_s", "°/s", RAD_TO_DEG] : ["m_s2", "m/s²", 1]);
const CSV_COLUMNS = "time_s, specific_force_x_m_s2, specific_force_y_m_s2, specific_force_z_m_s2 (optional: angular_velocity_x_rad_s, _y_, _z_)";

function numberInput(fieldPath, value, scale, unit) {
  return h("input", { type: "number", step: "any", value: value === null || value === undefined ? "" : +(value * scale).toFixed(4),
    "data-field": fieldPath, "data-scale": String(scale), "data-unit": unit });
}

// Multisine: a list of sine components, each on its own axis.
function componentsEditor(prefix, components) {
  const host = h("div.components");
  let rows = [];
  const render = (list) => {
    clear(host);
    rows = list.map((component, k) => {
      const path = `${prefix}.cue.components[${k}]`;
      const axis = h("select", { "data-field": `${path}.axis` }, AXES.map((a) => h("option", { value: a, selected: a === (component.axis || "y") }, AXIS_WORDS[a])));
      const [unitKey, unit, scale] = axisUnit(axis.value);
      const amplitude = numberInput(`${path}.amplitude_${unitKey}`, component[`amplitude_${unitKey}`] ?? 0.3, scale, unit);
      const frequency = numberInput(`${path}.frequency_hz`, component.frequency_hz ?? 0.3 * (k + 1), 1, "Hz");
      const phase = numberInput(`${path}.phase_rad`, component.phase_rad ?? 0, RAD_TO_DEG, "°");
      axis.addEventListener("change", () => render(read()));
      const row = h("div.form-grid.component", {},
        field(`Component ${k + 1}: axis`, axis), field(`Component ${k + 1}: amplitude`, amplitude, { unit }),
        field(`Component ${k + 1}: frequency`, frequency, { unit: "Hz" }), field(`Component ${k + 1}: phase`, phase, { unit: "°" }),
        list.length > 1 ? h("div.field", {}, h("button.secondary", { type: "button", onclick: () => { const next = read(); next.splice(k, 1); render(next); } }, `Remove component ${k + 1}`)) : null);
      row.read = () => {
        const [key, , factor] = axisUnit(axis.value);
        const spec = { axis: axis.value, [`amplitude_${key}`]: Number(amplitude.value) / factor, frequency_hz: Number(frequency.value) };
        if (phase.value !== "" && Number(phase.value) !== 0) spec.phase_rad = Number(phase.value) / RAD_TO_DEG;
        return spec;
      };
      return row;
    });
    host.append(...rows, h("button.secondary", { type: "button", onclick: () => { const next = read(); next.push({ axis: "y" }); render(next); } }, "Add a component"));
  };
  const read = () => rows.map((row) => row.read());
  render(components && components.length ? components : [{ axis: "y", amplitude_m_s2: 0.3, frequency_hz: 0.2 }, { axis: "y", amplitude_m_s2: 0.2, frequency_hz: 0.45 }]);
  host.read = read;
  return host;
}

// A recorded cue: the CSV file is read in the browser and sent as text; core.cues checks it.
function csvEditor(prefix, csv) {
  let text = csv || "";
  const summary = h("p.hint", { role: "status" });
  const describe = () => {
    if (!text) { summary.textContent = `No file yet. Columns: ${CSV_COLUMNS}.`; return; }
    const lines = text.trim().split(/\r?\n/);
    summary.textContent = `${lines.length - 1} rows loaded; columns: ${lines[0]}.`;
  };
  const upload = h("input", { type: "file", accept: ".csv,text/csv", "data-field": `${prefix}.cue.csv`, "data-label": "Recorded cue (CSV)" });
  upload.addEventListener("change", async () => { text = upload.files[0] ? await upload.files[0].text() : text; describe(); });
  describe();
  const host = h("div", {}, field("Recorded cue (CSV file)", upload, { hint: `Columns: ${CSV_COLUMNS}. Times in s, from 0, increasing.` }), summary);
  host.read = () => text;
  return host;
}

function segmentEditor(index, segment, onRemove) {
  const cue = segment.cue || { kind: "sine", axis: "y", amplitude_m_s2: 0.5, frequency_hz: 0.5 };
  const prefix = `segments[${index}]`;
  const kind = h("select", { "data-field": `${prefix}.cue.kind` }, Object.keys(CUE_FIELDS).map((k) => h("option", { value: k, selected: k === cue.kind }, KIND_WORDS[k])));
  const axis = h("select", { "data-field": `${prefix}.cue.axis` }, AXES.map((a) => h("option", { value: a, selected: a === (cue.axis || "y") }, AXIS_WORDS[a])));
  const duration = h("input", { type: "number", step: "1", min: "1", value: segment.duration_s ?? 60, "data-field": `${prefix}.duration_s` });
  const tilt = h("input", { type: "number", step: "0.5", min: "0", placeholder: "robot's", "data-field": `${prefix}.limits.tilt_max_rad`,
    "data-scale": String(RAD_TO_DEG), value: segment.limits && segment.limits.tilt_max_rad ? (segment.limits.tilt_max_rad * RAD_TO_DEG).toFixed(1) : "" });
  const cueFields = h("div.form-grid");
  let inputs = {};
  let special = null;
  const renderCueFields = (source) => {
    clear(cueFields);
    inputs = {};
    special = null;
    const [unitKey, axisUnitShown, axisScale] = axisUnit(axis.value);
    for (const [name, label, unit, factor, fallback] of CUE_FIELDS[kind.value]) {
      const apiName = AXIS_VALUES.has(name) ? `${name}_${unitKey}` : name;
      const shownUnit = AXIS_VALUES.has(name) ? axisUnitShown : unit;
      const scale = AXIS_VALUES.has(name) ? axisScale : factor;
      // A value typed for the other kind of axis is carried over in the new unit's SI value.
      const otherName = AXIS_VALUES.has(name) ? `${name}_${unitKey === "m_s2" ? "rad_s" : "m_s2"}` : apiName;
      const current = source[apiName] ?? source[otherName];
      const input = numberInput(`${prefix}.cue.${apiName}`, current !== undefined ? current : fallback, scale, shownUnit);
      if (current === undefined && fallback !== null) input.value = fallback;
      inputs[apiName] = [input, scale, fallback === null];
      cueFields.append(field(label, input, { unit: shownUnit }));
    }
    if (kind.value === "multisine") { special = componentsEditor(prefix, source.components); cueFields.append(special); }
    if (kind.value === "csv_replay") { special = csvEditor(prefix, source.csv); cueFields.append(special); }
    cueFields.classList.toggle("wide", Boolean(special));
    axis.closest(".field").hidden = !AXIS_KINDS.has(kind.value);
  };
  const box = h("div.segment", { dataset: { segment: index } },
    h("div.row", {}, h("h3.grow", {}, `Segment ${index + 1}`),
      onRemove ? h("button.secondary", { type: "button", onclick: onRemove }, `Remove segment ${index + 1}`) : null),
    h("div.form-grid", {}, field("Cue", kind), field("Axis", axis), field("Duration", duration, { unit: "s" }),
      field("Tilt limit (optional, may only tighten)", tilt, { unit: "°" })),
    cueFields);
  kind.addEventListener("change", () => renderCueFields({}));
  axis.addEventListener("change", () => renderCueFields(Object.fromEntries(Object.entries(inputs).map(([name, [input, scale]]) => [name, input.value === "" ? undefined : Number(input.value) / scale]))));
  renderCueFields(cue);
  box.read = () => {
    const spec = { kind: kind.value };
    if (AXIS_KINDS.has(kind.value)) spec.axis = axis.value;
    for (const [name, [input, scale]] of Object.entries(inputs)) if (input.value !== "") spec[name] = Number(input.value) / scale;
    if (kind.value === "multisine") spec.components = special.read();
    if (kind.value === "csv_replay") spec.csv = special.read();
    const limits = {};
    if (tilt.value !== "") limits.tilt_max_rad = Number(tilt.value) / RAD_TO_DEG;
    const result = { cue: spec, duration_s: Number(duration.value), limits };
    if (segment.washout) result.washout = segment.washout;
    if (segment.shaping) result.shaping = segment.shaping; // kept on revision, as the washout is
    return result;
  };
  return box;
}

// `params`: patient (new prescription), protocol (a library programme to start from, js/protocols.js).
export async function prescriptionPage(main, prescriptionId, params) {
  const existing = prescriptionId ? await get(`/prescriptions/${prescriptionId}`) : null;
  const patientId = existing ? existing.patient_id : Number(params.get("patient"));
  const patient = await get(`/patients/${patientId}`);
  const protocol = !existing && params.get("protocol") ? protocolByKey(params.get("protocol")) : null;
  let segments = existing ? existing.current.content.segments.map((s) => ({ ...s }))
    : protocol ? protocol.segments.map((s) => structuredClone(s)) : [{}];
  const name = h("input", { value: existing ? existing.name : protocol ? protocol.name : "", "data-field": "name", required: true });
  const note = h("input", { value: protocol ? `From the protocol “${protocol.name}”` : "", "data-field": "note", placeholder: existing ? "What changed" : "" });
  // The algorithm for the whole prescription (issue 14): the paper's washout stays the default.
  const storedCueing = (existing && existing.current.content.cueing) || "classical";
  const cueing = h("select", { name: "cueing", "data-field": "cueing" },
    Object.entries(CUEING_WORDS).map(([value, label]) => h("option", { value, selected: value === storedCueing }, label)));
  const segmentHost = h("div.segments");
  const previewHost = h("div");
  // A preview on screen is computed again for the algorithm chosen, so it never shows the other one.
  cueing.addEventListener("change", () => {
    if (previewHost.childElementCount) runPreview(form, previewHost, readSegments(), patientId, cueing.value);
  });
  let editors = [];
  const renderSegments = () => {
    clear(segmentHost);
    editors = segments.map((s, i) => segmentEditor(i, s, segments.length > 1 ? () => { segments = readSegments(); segments.splice(i, 1); renderSegments(); } : null));
    segmentHost.append(...editors);
  };
  const readSegments = () => editors.map((e) => e.read());
  const form = h("form.panel", {
    novalidate: true,
    onsubmit: async (event) => {
      event.preventDefault();
      const body = { name: name.value, segments: readSegments(), note: note.value, cueing: cueing.value };
      // The robot's own check first: a prescription it would refuse is saved only on purpose.
      const verdict = await runPreview(form, previewHost, body.segments, patientId, body.cueing);
      if (verdict === null) return;
      if (!verdict.accepted) {
        const ok = await confirmDialog({ title: "The robot would refuse this prescription",
          body: `${rejectionWords(verdict.rejection)} It can be saved to finish later, but a session with it will not start.`,
          ok: "Save anyway" });
        if (!ok) return;
      }
      try {
        const saved = existing ? await put(`/prescriptions/${existing.id}`, body, { version: existing.latest_version }) : await post("/prescriptions", { patient_id: patientId, ...body });
        clearErrors("form");
        banner("info", `Prescription “${saved.name}” saved as version ${saved.latest_version}.`);
        go(`#/prescriptions/${saved.id}`);
      } catch (error) {
        showRefusal(form, error);
      }
    },
  },
  h("div.form-grid", {}, field("Prescription name", name), field("Version note", note),
    field("Motion cueing", cueing, { hint: "Classical: the paper's washout filter, tick by tick. Optimal: the platform's motion "
      + "planned over the whole prescription before it starts, within every limit of the robot." })),
  segmentHost,
  h("div.row", {},
    h("button.secondary", { type: "button", onclick: () => { segments = readSegments(); segments.push({}); renderSegments(); } }, "Add segment"),
    h("button.secondary", { type: "button", id: "preview-button", onclick: () => runPreview(form, previewHost, readSegments(), patientId, cueing.value) }, "Preview motion"),
    h("button.primary", { type: "submit" }, existing ? "Save as new version" : "Save prescription")));
  renderSegments();
  main.append(
    h("h1", {}, existing ? `Prescription: ${existing.name} (v${existing.latest_version})` : "New prescription"),
    h("p", {}, "For ", h("a", { href: `#/patients/${patientId}` }, patient.name), `: ${fmt(patient.body_mass_kg, "kg", 0)}, ${fmt(patient.height_m * 100, "cm", 0)}.`,
      protocol ? ` Started from the protocol “${protocol.name}”: adapt it to the patient, preview, then save.` : ""),
    existing ? h("p#prescription-cueing", {}, h("strong", {}, "Motion cueing: "), CUEING_WORDS[storedCueing]) : "",
    form, previewHost);
  name.focus();
}

// Runs the preview; returns the verdict, or null when the prescription itself was refused (shown at its fields).
// The preview is a job of the robot's planner (issue 21, defect 6): posted, then polled for its progress.
// A preview asked for while another is computed supersedes it: only the latest is shown (null for the rest).
const PREVIEW_POLL_MS = 250;
async function runPreview(form, host, segments, patientId, cueing) {
  const ticket = (host.previewTicket = (host.previewTicket || 0) + 1);
  const bar = h("progress", { max: 100, value: 0, "aria-label": "Preview computed so far" });
  const percent = h("span", {}, "0 %");
  clear(host).append(h("p.panel", { role: "status" },
    `Computing the preview (${CUEING_WORDS[cueing]}) through the robot's own pipeline… `, bar, " ", percent));
  try {
    let job = await post("/prescriptions/previews", { segments, patient_id: patientId, cueing });
    while (job.state === "planning") {
      if (host.previewTicket !== ticket) return null;
      bar.value = Math.round(job.progress * 100);
      percent.textContent = `${bar.value} %`;
      await new Promise((resolve) => setTimeout(resolve, PREVIEW_POLL_MS));
      job = await get(`/prescriptions/previews/${job.preview_id}`);
    }
    if (host.previewTicket !== ticket) return null;
    // A refusal found while planning reads as the 422 of the prescription itself: shown at its field.
    if (job.state === "refused") throw new ApiError(422, job.refusal);
    if (job.state !== "ready") throw new Error(`the preview could not be computed: ${job.error}`);
    showFieldErrors(form, {});
    clearErrors("form");
    renderPreview(clear(host), job.preview);
    return job.preview.verdict;
  } catch (error) {
    if (host.previewTicket !== ticket) return null;
    clear(host);
    showRefusal(form, error);
    return null;
  }
}

function renderPreview(host, p) {
  const verdict = p.verdict.accepted
    ? h("p.verdict.ok", {}, `The robot accepts this prescription: ${fmt(p.duration_s, "s", 1)} in all; highest use of a limit `,
      `${Math.round(Math.max(...Object.values(p.verdict.report.peak_use)) * 100)} %.`)
    : h("p.verdict.bad", { role: "alert" }, `The robot would refuse this prescription. ${rejectionWords(p.verdict.rejection)}`,
      h("details.raw", {}, h("summary", {}, "technical details"), h("pre", {}, p.verdict.rejection.message)));
  const charts = h("div.charts");
  const algorithm = CUEING_WORDS[p.cueing];
  host.append(h("h2", {}, "Preview"), h("p#preview-cueing", {}, h("strong", {}, "Motion cueing: "), algorithm), verdict, charts);
  const t = p.time_s;
  const axes = ["x (AP)", "y (ML)", "z"];
  staticChart(charts, "Platform position", "mm", t, p.platform_position_m.map((c) => c.map((v) => (v == null ? null : v * M_TO_MM))),
    axes.map((a) => ({ label: a, digits: 1 })));
  staticChart(charts, "Platform angles", "°", t, p.platform_angles_rad.map((c) => c.map((v) => (v == null ? null : v * RAD_TO_DEG))),
    ["roll", "pitch", "yaw"].map((a) => ({ label: a })));
  const perceived = [];
  const series = [];
  [0, 1].forEach((k) => {
    perceived.push(p.perceived_cue_m_s2[k], p.perceived_platform_m_s2[k]);
    series.push({ label: `cue ${axes[k]}`, color: k ? "#d1495b" : "#0b4fa8", dash: [8, 5] }, { label: `platform ${axes[k]}`, color: k ? "#d1495b" : "#0b4fa8" });
  });
  staticChart(charts, `Perceived acceleration at the head (${fmt(p.head_height_m * 100, "cm", 0)} above the feet, otolith model): `
    + `cue (dashed) vs delivered by ${algorithm}`, "m/s²", t, perceived, series);
  tiltRateChart(charts, p);
  const travel = p.slider_position_m.map((column, i) => column.map((v) => (v == null ? null
    : (100 * (v - p.stroke_min_m[i])) / (p.stroke_max_m[i] - p.stroke_min_m[i]))));
  staticChart(charts, "Slider travel within the stroke (0 % and 100 % = stroke ends)", "%", t, travel,
    travel.map((_, i) => ({ label: `${i < 6 ? "R" : "L"}${(i % 6) + 1}`, dash: i < 6 ? undefined : [6, 4], width: 1.5 })), { yRange: [0, 100] });
}

// Roll and pitch rate of the platform beyond what the cue asks for, against the canal threshold the optimal
// planner keeps (core.optimal_cueing defaults: 3 °/s roll, 3.6 °/s pitch): above it the patient feels the
// tilt as a rotation. Differenced from the plotted samples, so a peak shorter than their spacing is smoothed.
const TILT_RATE_THRESHOLDS_DEG_S = [3.0, 3.6];
function tiltRateChart(charts, p) {
  const t = p.time_s;
  const uncued = [0, 1].map((k) => t.map((_, i) => {
    const j = Math.max(i - 1, 0), l = Math.min(i + 1, t.length - 1);
    const [a, b] = [p.platform_angles_rad[k][j], p.platform_angles_rad[k][l]];
    if (a == null || b == null || l === j) return null;
    return Math.abs((b - a) / (t[l] - t[j]) - p.cue_angular_velocity_rad_s[k][i]) * RAD_TO_DEG;
  }));
  const spacingMs = t.length > 1 ? ((t[t.length - 1] - t[0]) / (t.length - 1)) * 1000 : 0;
  staticChart(charts, `Tilt rate the cue does not ask for, against the perception threshold (from samples ${fmt(spacingMs, "ms", 0)} apart)`, "°/s", t,
    [...uncued, ...TILT_RATE_THRESHOLDS_DEG_S.map((v) => t.map(() => v))],
    [{ label: "roll" }, { label: "pitch" },
      { label: "roll threshold", color: "#0b4fa8", dash: [4, 4], width: 1 }, { label: "pitch threshold", color: "#d1495b", dash: [4, 4], width: 1 }],
    { yRange: (u, min, max) => [0, Math.max(max ?? 0, 4.5)] });
}

// --- schedule: the clinic-local week view lives in schedule.js ------------------------------------
export { schedulePage } from "./schedule.js";

// --- session history: every booking of the last weeks with its runs and exports --------------------
export async function historyPage(main, params) {
  const days = Number(params.get("days") || 30);
  const from = new Date(Date.now() - days * 86400000);
  const [bookings, patients] = await Promise.all([
    get(`/sessions${query({ from: from.toISOString(), to: new Date(Date.now() + 366 * 86400000).toISOString(), limit: 500 })}`),
    get("/patients?limit=500"),
  ]);
  const names = Object.fromEntries(patients.map((p) => [p.id, p.name]));
  main.append(h("h1", {}, "Session history"), h("p.muted", {}, `Bookings from the last ${days} days and ahead; open one to see its runs, events and exports.`));
  const rows = await Promise.all(bookings.reverse().map(async (b) => {
    const runs = await get(`/sessions/${b.id}/runs`);
    return h("tr", {}, h("td", {}, fmtDateTime(b.start)), h("td", {}, names[b.patient_id] || b.patient_id), h("td", {}, b.robot),
      h("td", {}, badge(b.status)), h("td.num", {}, runs.length),
      h("td", {}, runs.length ? badge(runs[runs.length - 1].outcome || runs[runs.length - 1].state) : "—"),
      h("td", {}, h("a.button", { href: `#/session/${b.id}` }, "Open"), " ", reportLink(runs[runs.length - 1])));
  }));
  main.append(rows.length ? table(["Booked for", "Patient", "Robot", "Booking", "Runs", "Last outcome", ""], rows) : h("p", {}, "No sessions."));
}

