// Login, patients, patient profile, prescription editor, schedule week view and session history.
import { get, patch, post, put, query } from "./api.js";
import { staticChart } from "./charts.js";
import {
  M_TO_MM, RAD_TO_DEG, badge, banner, clear, field, fmt, fmtDateTime, fmtTime, h,
  showError, showFieldErrors, table,
} from "./ui.js";

const go = (hash) => { location.hash = hash; };

// --- login ---------------------------------------------------------------------------------------
export function loginPage(main, { onLogin }) {
  const username = h("input", { name: "username", autocomplete: "username", required: true, "data-field": "username" });
  const password = h("input", { name: "password", type: "password", autocomplete: "current-password", required: true, "data-field": "password" });
  const form = h("form.panel.login", {
    onsubmit: async (event) => {
      event.preventDefault();
      try {
        const result = await post("/auth/login", { username: username.value, password: password.value });
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
  const results = h("div");
  const load = async () => {
    const patients = await get(`/patients${query({ search: search.value.trim() })}`);
    clear(results).append(patients.length ? table(
      ["Record number", "Name", "Date of birth", "Diagnosis", ""],
      patients.map((p) => h("tr.clickable", {},
        h("td", {}, p.identifier), h("td", {}, p.name), h("td", {}, p.date_of_birth), h("td", {}, p.diagnosis || "—"),
        h("td", {}, h("a.button", { href: `#/patients/${p.id}` }, "Open profile")))),
    ) : h("p.muted", {}, "No patient matches."));
  };
  let timer = null;
  search.addEventListener("input", () => { clearTimeout(timer); timer = setTimeout(() => load().catch(showError), 250); });
  main.append(h("h1", {}, "Patients"),
    h("div.row", {}, h("div.grow", {}, field("Search", search)),
      h("button.primary", { type: "button", onclick: () => go("#/patients/new") }, "New patient")),
    results);
  search.focus();
  await load();
}

export function newPatientPage(main) {
  const input = (name, attrs = {}) => h("input", { name, "data-field": name, ...attrs });
  const select = (name, options) => h("select", { name, "data-field": name }, options.map((o) => h("option", { value: o }, o)));
  const f = {
    identifier: input("identifier", { required: true }),
    name: input("name", { required: true }),
    date_of_birth: input("date_of_birth", { type: "date", required: true }),
    sex: select("sex", SEXES),
    height_m: input("height_m", { type: "number", step: "1", min: "50", max: "250", required: true }),
    body_mass_kg: input("body_mass_kg", { type: "number", step: "0.1", min: "10", max: "250", required: true }),
    diagnosis: input("diagnosis"),
    affected_side: select("affected_side", SIDES),
    contraindications: h("textarea", { name: "contraindications", "data-field": "contraindications", rows: 2 }),
    notes: h("textarea", { name: "notes", "data-field": "notes", rows: 2 }),
  };
  const form = h("form.panel", {
    novalidate: true,
    onsubmit: async (event) => {
      event.preventDefault();
      const body = {
        identifier: f.identifier.value, name: f.name.value, date_of_birth: f.date_of_birth.value, sex: f.sex.value,
        height_m: Number(f.height_m.value) / 100, body_mass_kg: Number(f.body_mass_kg.value), diagnosis: f.diagnosis.value,
        affected_side: f.affected_side.value, contraindications: f.contraindications.value, notes: f.notes.value,
      };
      try {
        const patient = await post("/patients", body);
        banner("info", `Patient ${patient.name} created.`);
        go(`#/patients/${patient.id}`);
      } catch (error) {
        const unplaced = error.status === 422 ? showFieldErrors(form, error.fieldErrors) : [];
        if (error.status !== 422 || unplaced.length) showError(error, "form");
      }
    },
  },
  h("div.form-grid", {},
    field("Record number", f.identifier), field("Name", f.name), field("Date of birth", f.date_of_birth), field("Sex", f.sex),
    field("Height", f.height_m, { unit: "cm" }), field("Body mass", f.body_mass_kg, { unit: "kg" }),
    field("Diagnosis", f.diagnosis), field("Affected side", f.affected_side)),
  field("Contraindications", f.contraindications), field("Notes", f.notes),
  h("div.row", {}, h("button.primary", { type: "submit" }, "Create patient"), h("a.button", { href: "#/patients" }, "Cancel")));
  main.append(h("h1", {}, "New patient"), form);
  f.identifier.focus();
}

export async function patientPage(main, patientId) {
  const [patient, prescriptions, bookings, trend] = await Promise.all([
    get(`/patients/${patientId}`),
    get(`/prescriptions${query({ patient_id: patientId })}`),
    get(`/sessions${query({ patient_id: patientId, limit: 200 })}`),
    get(`/patients/${patientId}/balance`).catch(() => []),
  ]);
  main.append(
    h("h1", {}, `${patient.name} `, h("span.muted", {}, `(${patient.identifier})`)),
    h("div.panel.metrics", {},
      metric("Date of birth", patient.date_of_birth), metric("Sex", patient.sex),
      metric("Height", fmt(patient.height_m * 100, "cm", 0)), metric("Body mass", fmt(patient.body_mass_kg, "kg", 1)),
      metric("Diagnosis", patient.diagnosis || "—"), metric("Affected side", patient.affected_side)),
    h("p", {}, h("strong", {}, "Contraindications: "), patient.contraindications || "none recorded"),
    h("h2", {}, "Prescriptions"),
    h("div.row", {}, h("a.button.primary", { href: `#/prescriptions/new?patient=${patientId}` }, "New prescription"),
      h("a.button", { href: `#/schedule?patient=${patientId}` }, "Schedule a session")),
    prescriptions.length ? table(["Name", "Version", "Segments", "Total duration", ""], prescriptions.map((p) => h("tr", {},
      h("td", {}, p.name), h("td.num", {}, `v${p.latest_version}`), h("td.num", {}, p.current.content.segments.length),
      h("td.num", {}, fmt(p.current.content.segments.reduce((s, x) => s + x.duration_s, 0), "s", 0)),
      h("td", {}, h("a.button", { href: `#/prescriptions/${p.id}` }, "Edit / preview"))))) : h("p.muted", {}, "No prescription yet."),
  );
  const falls = trend.reduce((sum, run) => sum + run.falls, 0);
  main.append(h("h2", {}, "Balance trend"), h("p", {}, `${trend.length} recorded run(s), ${falls} fall(s).`));
  const measured = trend.filter((run) => run.sway);
  if (measured.length) {
    const charts = h("div.charts");
    main.append(charts);
    const x = measured.map((_, i) => i + 1);
    staticChart(charts, "COP sway: RMS distance and 95 % ellipse", "mm / cm²", x,
      [measured.map((r) => r.sway.rms_distance_m * M_TO_MM), measured.map((r) => r.sway.ellipse_area_95_m2 * 1e4)],
      [{ label: "RMS distance (mm)" }, { label: "95 % ellipse area (cm²)" }], { xLabel: "run number" });
    staticChart(charts, "COP mean velocity and falls", "mm/s / count", x,
      [measured.map((r) => r.sway.mean_velocity_m_s * M_TO_MM), measured.map((r) => r.falls)],
      [{ label: "Mean COP velocity (mm/s)" }, { label: "Falls (count)" }], { xLabel: "run number" });
  } else {
    main.append(h("p.muted", {}, "No run with force-plate data yet: the trend appears after the first session."));
  }
  main.append(h("h2", {}, "Session history"), await sessionsTable(bookings.slice().reverse()));
}

function metric(label, value, bad = false) {
  return h(`div.metric${bad ? ".bad" : ""}`, {}, h("div.label", {}, label), h("div.value", {}, value));
}
export { metric };

async function sessionsTable(bookings) {
  if (!bookings.length) return h("p.muted", {}, "No session yet.");
  const rows = await Promise.all(bookings.map(async (b) => {
    const runs = await get(`/sessions/${b.id}/runs`);
    const last = runs[runs.length - 1];
    return h("tr", {},
      h("td", {}, fmtDateTime(b.start)), h("td", {}, badge(b.status)), h("td.num", {}, runs.length),
      h("td", {}, last ? badge(last.outcome || last.state) : "—"),
      h("td", {}, h("a.button", { href: `#/session/${b.id}` }, "Open")));
  }));
  return table(["Booked for", "Booking", "Runs", "Last outcome", ""], rows);
}

// --- prescription editor -------------------------------------------------------------------------
// Cue fields by kind: [name, label, unit shown, factor from the API's SI value to the unit shown, default].
const AXES = ["x", "y", "z", "roll", "pitch", "yaw"];
const ROTATION = new Set(["roll", "pitch", "yaw"]);
const CUE_FIELDS = {
  sine: [["amplitude", "Amplitude", null, null, 0.5], ["frequency_hz", "Frequency", "Hz", 1, 0.5]],
  square_wave: [["amplitude", "Amplitude", null, null, 0.5], ["period_s", "Period", "s", 1, 4], ["duty", "Duty cycle", "fraction", 1, 0.5]],
  perturbations: [["translation_m_s2", "Translation pulse", "m/s²", 1, 1.0], ["tilt_rate_rad_s", "Tilt rate pulse", "°/s", RAD_TO_DEG, 0],
    ["pulse_duration_s", "Pulse duration", "s", 1, 0.5], ["interval_min_s", "Shortest interval", "s", 1, 3], ["interval_max_s", "Longest interval", "s", 1, 8]],
  gait: [["cadence_steps_per_min", "Cadence", "steps/min", 1, 90], ["lateral_amplitude_m_s2", "Lateral amplitude", "m/s²", 1, 0.5],
    ["forward_amplitude_m_s2", "Forward amplitude", "m/s²", 1, 0.3], ["vertical_amplitude_m_s2", "Vertical amplitude", "m/s²", 1, 0]],
};
const AXIS_KINDS = new Set(["sine", "square_wave"]);

function segmentEditor(index, segment, onRemove) {
  const cue = segment.cue || { kind: "sine", axis: "y", amplitude_m_s2: 0.5, frequency_hz: 0.5 };
  const prefix = `segments[${index}]`;
  const kind = h("select", { "data-field": `${prefix}.cue.kind` }, Object.keys(CUE_FIELDS).map((k) => h("option", { value: k, selected: k === cue.kind }, k.replace("_", " "))));
  const axis = h("select", { "data-field": `${prefix}.cue.axis` }, AXES.map((a) => h("option", { value: a, selected: a === cue.axis }, a)));
  const duration = h("input", { type: "number", step: "1", min: "1", value: segment.duration_s ?? 60, "data-field": `${prefix}.duration_s` });
  const tilt = h("input", { type: "number", step: "0.5", min: "0", placeholder: "robot limit", "data-field": `${prefix}.limits.tilt_max_rad`,
    value: segment.limits && segment.limits.tilt_max_rad ? (segment.limits.tilt_max_rad * RAD_TO_DEG).toFixed(1) : "" });
  const cueFields = h("div.form-grid");
  let inputs = {};
  const renderCueFields = (source) => {
    clear(cueFields);
    inputs = {};
    const rotational = ROTATION.has(axis.value);
    for (const [name, label, unit, factor, fallback] of CUE_FIELDS[kind.value]) {
      const apiName = name === "amplitude" ? (rotational ? "amplitude_rad_s" : "amplitude_m_s2") : name;
      const shownUnit = name === "amplitude" ? (rotational ? "°/s" : "m/s²") : unit;
      const scale = name === "amplitude" ? (rotational ? RAD_TO_DEG : 1) : factor;
      const current = source[apiName] ?? source[name === "amplitude" ? (rotational ? "amplitude_m_s2" : "amplitude_rad_s") : apiName];
      const input = h("input", { type: "number", step: "any", value: current !== undefined ? +(current * scale).toFixed(4) : fallback,
        "data-field": `${prefix}.cue.${apiName}` });
      inputs[apiName] = [input, scale];
      cueFields.append(field(label, input, { unit: shownUnit }));
    }
    axis.closest(".field").hidden = !AXIS_KINDS.has(kind.value);
  };
  const box = h("div.segment", { dataset: { segment: index } },
    h("div.row", {}, h("h3.grow", {}, `Segment ${index + 1}`),
      onRemove ? h("button.secondary", { type: "button", onclick: onRemove }, `Remove segment ${index + 1}`) : null),
    h("div.form-grid", {}, field("Cue", kind), field("Axis", axis), field("Duration", duration, { unit: "s" }),
      field("Tilt limit (optional, may only tighten)", tilt, { unit: "°" })),
    cueFields);
  kind.addEventListener("change", () => renderCueFields({}));
  axis.addEventListener("change", () => renderCueFields({}));
  renderCueFields(cue);
  box.read = () => {
    const spec = { kind: kind.value };
    if (AXIS_KINDS.has(kind.value)) spec.axis = axis.value;
    for (const [name, [input, scale]] of Object.entries(inputs)) if (input.value !== "") spec[name] = Number(input.value) / scale;
    const limits = {};
    if (tilt.value !== "") limits.tilt_max_rad = Number(tilt.value) / RAD_TO_DEG;
    const result = { cue: spec, duration_s: Number(duration.value), limits };
    if (segment.washout) result.washout = segment.washout;
    return result;
  };
  return box;
}

export async function prescriptionPage(main, prescriptionId, params) {
  const existing = prescriptionId ? await get(`/prescriptions/${prescriptionId}`) : null;
  const patientId = existing ? existing.patient_id : Number(params.get("patient"));
  const patient = await get(`/patients/${patientId}`);
  let segments = existing ? existing.current.content.segments.map((s) => ({ ...s })) : [{}];
  const name = h("input", { value: existing ? existing.name : "", "data-field": "name", required: true });
  const note = h("input", { value: "", "data-field": "note", placeholder: existing ? "What changed in this version" : "" });
  const segmentHost = h("div.segments");
  const previewHost = h("div");
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
      const body = { name: name.value, segments: readSegments(), note: note.value };
      try {
        const saved = existing ? await put(`/prescriptions/${existing.id}`, body) : await post("/prescriptions", { patient_id: patientId, ...body });
        banner("info", `Prescription “${saved.name}” saved as version ${saved.latest_version}.`);
        go(`#/prescriptions/${saved.id}`);
      } catch (error) {
        const unplaced = error.status === 422 ? showFieldErrors(form, error.fieldErrors) : [];
        if (error.status !== 422 || unplaced.length) showError(error, "form");
      }
    },
  },
  h("div.form-grid", {}, field("Prescription name", name), field("Version note", note)),
  segmentHost,
  h("div.row", {},
    h("button.secondary", { type: "button", onclick: () => { segments = readSegments(); segments.push({}); renderSegments(); } }, "Add segment"),
    h("button.secondary", { type: "button", id: "preview-button", onclick: () => runPreview(form, previewHost, readSegments(), patientId) }, "Preview motion"),
    h("button.primary", { type: "submit" }, existing ? "Save as new version" : "Save prescription")));
  renderSegments();
  main.append(
    h("h1", {}, existing ? `Prescription: ${existing.name} (v${existing.latest_version})` : "New prescription"),
    h("p", {}, "For ", h("a", { href: `#/patients/${patientId}` }, patient.name), `: ${fmt(patient.body_mass_kg, "kg", 0)}, ${fmt(patient.height_m * 100, "cm", 0)}.`),
    form, previewHost);
  name.focus();
}

async function runPreview(form, host, segments, patientId) {
  clear(host).append(h("p.panel", { role: "status" }, "Computing the preview through the robot's own pipeline…"));
  try {
    const preview = await post("/prescriptions/preview", { segments, patient_id: patientId });
    showFieldErrors(form, {});
    renderPreview(clear(host), preview);
  } catch (error) {
    clear(host);
    const unplaced = error.status === 422 ? showFieldErrors(form, error.fieldErrors) : [];
    if (error.status !== 422 || unplaced.length) showError(error, "form");
  }
}

function renderPreview(host, p) {
  const verdict = p.verdict.accepted
    ? h("p.verdict.ok", {}, `The robot accepts this prescription: ${fmt(p.duration_s, "s", 1)} in all; highest use of a limit `,
      `${Math.round(Math.max(...Object.values(p.verdict.report.peak_use)) * 100)} %.`)
    : h("p.verdict.bad", { role: "alert" }, `The robot would refuse this prescription: ${p.verdict.rejection.message}`);
  const charts = h("div.charts");
  host.append(h("h2", {}, "Preview"), verdict, charts);
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
  staticChart(charts, "Perceived acceleration: cue (dashed) vs platform (otolith model)", "m/s²", t, perceived, series);
  const travel = p.slider_position_m.map((column, i) => column.map((v) => (v == null ? null
    : (100 * (v - p.stroke_min_m[i])) / (p.stroke_max_m[i] - p.stroke_min_m[i]))));
  staticChart(charts, "Slider travel within the stroke (0 % and 100 % = stroke ends)", "%", t, travel,
    travel.map((_, i) => ({ label: `${i < 6 ? "R" : "L"}${(i % 6) + 1}`, dash: i < 6 ? undefined : [6, 4], width: 1.5 })), { yRange: [0, 100] });
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
      h("td", {}, h("a.button", { href: `#/session/${b.id}` }, "Open")));
  }));
  main.append(rows.length ? table(["Booked for", "Patient", "Robot", "Booking", "Runs", "Last outcome", ""], rows) : h("p", {}, "No sessions."));
}

