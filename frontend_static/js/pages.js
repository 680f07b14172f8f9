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
    get(`/patients/${patientId}/trends`).catch(() => null),
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
  } else {
    main.append(h("p.muted", {}, "No run with force-plate data yet: the trend appears after the first session."));
  }
  main.append(h("h2", {}, "Session history"), await sessionsTable(bookings.slice().reverse()));
}

// Balance trends by date (GET /patients/{id}/trends): one chart per series with its one unit on the y-axis;
// falls and faulted runs are drawn as red points over the line.
function trendCharts(host, trends) {
  const charts = h("div.charts");
  host.append(charts);
  for (const series of trends.series) {
    if (!series.points.length) continue;
    const x = series.points.map((p) => Date.parse(p.started_at) / 1000);
    const values = series.points.map((p) => p.value);
    const marked = series.points.map((p) => (p.status === "ok" ? null : p.value));
    const shown = (u, v) => (v == null ? "—" : `${v.toFixed(series.key === "falls" ? 0 : 1)} ${series.unit}`);
    const box = h("div.chart", { role: "img", "aria-label": `${series.label} by date, ${series.unit}` });
    charts.append(box);
    const plot = new uPlot({
      title: `${series.label} (${series.unit})`,
      width: 600,
      height: 220,
      scales: { x: { time: true } },
      axes: [
        { label: "date", stroke: "#111", grid: { stroke: "#ddd" }, font: "14px system-ui", labelFont: "bold 14px system-ui" },
        { label: series.unit, stroke: "#111", grid: { stroke: "#ddd" }, font: "14px system-ui", labelFont: "bold 14px system-ui", size: 64 },
      ],
      series: [
        { label: "date", value: (u, v) => (v == null ? "—" : new Date(v * 1000).toLocaleString()) },
        { label: series.label, stroke: "#0b4fa8", width: 2, points: { show: true, size: 6 }, value: shown },
        { label: "fall or faulted run", stroke: "#d1495b", width: 0, paths: () => null,
          points: { show: true, size: 11, fill: "#d1495b" }, value: shown },
      ],
    }, [x, values, marked], box);
    plot.setSize({ width: Math.max(320, (box.clientWidth || 600) - 12), height: 220 });
  }
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

// --- schedule: a week view -----------------------------------------------------------------------
function mondayOf(date) {
  const d = new Date(date);
  d.setHours(0, 0, 0, 0);
  d.setDate(d.getDate() - ((d.getDay() + 6) % 7));
  return d;
}
function localInputValue(date) {
  const pad = (n) => String(n).padStart(2, "0");
  return `${date.getFullYear()}-${pad(date.getMonth() + 1)}-${pad(date.getDate())}T${pad(date.getHours())}:${pad(date.getMinutes())}`;
}
const isoWithOffset = (localValue) => new Date(localValue).toISOString();

export async function schedulePage(main, params) {
  const week = mondayOf(params.get("week") || new Date());
  const end = new Date(week); end.setDate(end.getDate() + 7);
  const [bookings, patients] = await Promise.all([
    get(`/sessions${query({ from: week.toISOString(), to: end.toISOString(), limit: 500 })}`),
    get("/patients?limit=500"),
  ]);
  const patientName = Object.fromEntries(patients.map((p) => [p.id, p.name]));
  const shift = (days) => { const d = new Date(week); d.setDate(d.getDate() + days); go(`#/schedule?week=${d.toISOString().slice(0, 10)}`); };
  main.append(h("h1", {}, `Schedule: week of ${week.toLocaleDateString(undefined, { day: "numeric", month: "long", year: "numeric" })}`),
    h("div.row", {}, h("button.secondary", { type: "button", onclick: () => shift(-7) }, "← Previous week"),
      h("button.secondary", { type: "button", onclick: () => go("#/schedule") }, "This week"),
      h("button.secondary", { type: "button", onclick: () => shift(7) }, "Next week →")));
  const conflicts = overlapping(bookings.filter((b) => b.status !== "cancelled"));
  const days = h("div.week");
  for (let i = 0; i < 7; i += 1) {
    const day = new Date(week); day.setDate(day.getDate() + i);
    const next = new Date(day); next.setDate(next.getDate() + 1);
    const today = day.toDateString() === new Date().toDateString();
    days.append(h(`section.day${today ? ".today" : ""}`, { "aria-label": day.toDateString() },
      h("h3", {}, day.toLocaleDateString(undefined, { weekday: "long", day: "numeric", month: "short" })),
      bookings.filter((b) => new Date(b.start) >= day && new Date(b.start) < next).map((b) => h(
        `button.booking.${b.status}${conflicts.has(b.id) ? ".conflict" : ""}`,
        { type: "button", onclick: () => editBooking(b, patientName) },
        h("strong", {}, `${fmtTime(b.start)}–${fmtTime(b.end)}`), h("br"), patientName[b.patient_id] || `patient ${b.patient_id}`,
        h("br"), `${b.robot} · ${b.status}${conflicts.has(b.id) ? " · CONFLICT" : ""}`))));
  }
  main.append(days, bookingForm(patients, params));
}

function overlapping(bookings) {
  const ids = new Set();
  for (const a of bookings) for (const b of bookings) {
    if (a.id < b.id && (a.robot === b.robot || a.patient_id === b.patient_id) && new Date(a.start) < new Date(b.end) && new Date(b.start) < new Date(a.end)) {
      ids.add(a.id); ids.add(b.id);
    }
  }
  return ids;
}

function bookingForm(patients, params) {
  const patient = h("select", { "data-field": "patient_id" }, patients.map((p) => h("option", { value: p.id, selected: String(p.id) === params.get("patient") }, `${p.name} (${p.identifier})`)));
  const prescription = h("select", { "data-field": "prescription_id" });
  const start = h("input", { type: "datetime-local", "data-field": "start", value: localInputValue(nextQuarterHour()) });
  const duration = h("input", { type: "number", min: "1", max: "240", value: "30", "data-field": "duration_s" });
  const robot = h("input", { value: "twin-1", "data-field": "robot" });
  const repeat = h("select", { "data-field": "recurrence" }, [["", "once"], ["daily", "daily"], ["weekly", "weekly"]].map(([v, t]) => h("option", { value: v }, t)));
  const count = h("input", { type: "number", min: "2", max: "104", value: "6", "data-field": "recurrence.count" });
  const loadPrescriptions = async () => {
    const list = patient.value ? await get(`/prescriptions${query({ patient_id: patient.value })}`) : [];
    clear(prescription).append(...list.map((p) => h("option", { value: p.id }, `${p.name} (v${p.latest_version})`)));
  };
  patient.addEventListener("change", () => loadPrescriptions().catch(showError));
  loadPrescriptions().catch(showError);
  const form = h("form.panel", {
    novalidate: true,
    onsubmit: async (event) => {
      event.preventDefault();
      const body = {
        patient_id: Number(patient.value), prescription_id: Number(prescription.value), robot: robot.value,
        start: isoWithOffset(start.value), duration_s: Math.round(Number(duration.value) * 60),
      };
      if (repeat.value) body.recurrence = { frequency: repeat.value, interval: 1, count: Number(count.value) };
      try {
        const created = await post("/sessions", body);
        banner("info", `${created.length} session(s) booked.`);
        go(`#/schedule?week=${mondayOf(created[0].start).toISOString().slice(0, 10)}&booked=${created[0].id}`);
      } catch (error) {
        const errors = error.status === 422 ? error.fieldErrors : error.status === 409 ? { start: error.message } : {};
        if (errors.duration_s) errors.duration_s = errors.duration_s.replace(/(\d+)/g, (m) => `${m} s`);
        const unplaced = showFieldErrors(form, errors);
        if (!Object.keys(errors).length || unplaced.length) showError(error, "form");
      }
    },
  },
  h("h2", {}, "Book a session"),
  h("div.form-grid", {}, field("Patient", patient), field("Prescription", prescription), field("Start", start),
    field("Duration", duration, { unit: "min" }), field("Robot", robot), field("Repeat", repeat), field("Occurrences", count, { unit: "sessions" })),
  h("button.primary", { type: "submit" }, "Book session"));
  return form;
}
function nextQuarterHour() { const d = new Date(Date.now() + 15 * 60000); d.setMinutes(Math.ceil(d.getMinutes() / 15) * 15, 0, 0); return d; }

async function editBooking(booking, patientName) {
  const dialog = h("dialog", { "aria-labelledby": "booking-title" });
  const start = h("input", { type: "datetime-local", value: localInputValue(new Date(booking.start)), "data-field": "start" });
  const duration = h("input", { type: "number", min: "1", max: "240", value: String(booking.duration_s / 60), "data-field": "duration_s" });
  const form = h("form", { method: "dialog", novalidate: true },
    h("h2#booking-title", {}, `Session ${booking.id}: ${patientName[booking.patient_id] || ""}`),
    h("p", {}, `${fmtDateTime(booking.start)} on ${booking.robot}, ${booking.status}.`),
    field("Move to", start), field("Duration", duration, { unit: "min" }),
    h("div.dialog-buttons", {},
      h("a.button", { href: `#/session/${booking.id}`, onclick: () => dialog.close() }, "Open session console"),
      booking.status === "scheduled" ? h("button.danger", { type: "button", onclick: () => save({ status: "cancelled" }) }, "Cancel session") : null,
      h("button.secondary", { type: "button", onclick: () => dialog.close() }, "Close"),
      h("button.primary", { type: "button", onclick: () => save({ start: isoWithOffset(start.value), duration_s: Math.round(Number(duration.value) * 60) }) }, "Move")));
  async function save(change) {
    try {
      await patch(`/sessions/${booking.id}`, change);
      dialog.close();
      banner("info", change.status === "cancelled" ? "Session cancelled." : "Session moved.");
      window.dispatchEvent(new HashChangeEvent("hashchange"));
    } catch (error) {
      const errors = error.status === 422 ? error.fieldErrors : error.status === 409 ? { start: error.message } : {};
      const unplaced = showFieldErrors(form, errors);
      if (!Object.keys(errors).length || unplaced.length) showError(error, "form");
    }
  }
  dialog.append(form);
  document.body.append(dialog);
  dialog.addEventListener("close", () => dialog.remove());
  dialog.showModal();
}

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

