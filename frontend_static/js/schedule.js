// The schedule: one clinic-local week, booking and moving sessions, in the clinic's wall-clock time.
//
// Times come from the API as clinic-local ISO strings with their offset (`start_local`) and are shown as
// written there, whatever the browser's zone; bookings are sent as a clinic-local wall time without offset
// (`start_local`), which the service reads in its zone and refuses if it falls in a DST gap or overlap.
// Weeks are calendar dates (YYYY-MM-DD), computed in UTC date arithmetic so that no browser zone or DST
// change can move them; the service answers the previous and next week with each week.
import { get, patch, post, query, request } from "./api.js";
import { followPlan, planWords } from "./plan.js";
import { banner, clear, errorText, field, h, openDialog, showError, showFieldErrors } from "./ui.js";

const go = (hash) => { location.hash = hash; };

// --- calendar dates and clinic-local wall times, as strings ----------------------------------------
const ISO_DATE = /^\d{4}-\d{2}-\d{2}$/;
function dateParts(isoDate) { const [y, m, d] = isoDate.split("-").map(Number); return Date.UTC(y, m - 1, d); }
function addDays(isoDate, days) { return new Date(dateParts(isoDate) + days * 86400000).toISOString().slice(0, 10); }
function longDate(isoDate, options) {
  return new Date(dateParts(isoDate)).toLocaleDateString(undefined, { timeZone: "UTC", ...options });
}
const wallDate = (localIso) => localIso.slice(0, 10); // "2031-03-30T10:00:00+02:00" → "2031-03-30"
const wallTime = (localIso) => localIso.slice(11, 16); // → "10:00"
const wallInput = (localIso) => localIso.slice(0, 16); // → the datetime-local value "2031-03-30T10:00"

// Today and the next quarter hour on the clinic's clock (Intl with the clinic's IANA zone).
function clinicNow(timeZone, offsetMs = 0) {
  const parts = Object.fromEntries(new Intl.DateTimeFormat("en-CA", {
    timeZone, year: "numeric", month: "2-digit", day: "2-digit", hour: "2-digit", minute: "2-digit", hourCycle: "h23",
  }).formatToParts(new Date(Date.now() + offsetMs)).map((p) => [p.type, p.value]));
  return { date: `${parts.year}-${parts.month}-${parts.day}`, hour: Number(parts.hour), minute: Number(parts.minute) };
}
function nextQuarterHourInput(timeZone) {
  const soon = clinicNow(timeZone, 15 * 60000);
  const minutes = Math.ceil((soon.hour * 60 + soon.minute) / 15) * 15;
  const date = minutes >= 1440 ? addDays(soon.date, 1) : soon.date;
  const pad = (n) => String(n).padStart(2, "0");
  return `${date}T${pad(Math.floor((minutes % 1440) / 60))}:${pad(minutes % 60)}`;
}

function weekHash(monday, patientId, extra = {}) {
  const params = new URLSearchParams({ week: monday, ...(patientId ? { patient: String(patientId) } : {}), ...extra });
  return `#/schedule?${params}`;
}

// --- the week view ---------------------------------------------------------------------------------
export async function schedulePage(main, params) {
  const asked = params.get("week");
  const [week, patients] = await Promise.all([
    get(`/schedule/week${query({ day: asked && ISO_DATE.test(asked) ? asked : undefined })}`),
    get("/patients?limit=500"),
  ]);
  const monday = wallDate(week.start_local);
  const zone = week.timezone;
  const selectedPatient = params.get("patient");
  main.append(h("h1", {}, `Schedule: week of ${longDate(monday, { day: "numeric", month: "long", year: "numeric" })}`),
    h("div.row", {}, h("button.secondary", { type: "button", onclick: () => go(weekHash(week.previous_week, selectedPatient)) }, "← Previous week"),
      h("button.secondary", { type: "button", onclick: () => go(weekHash(clinicNow(zone).date, selectedPatient)) }, "This week"),
      h("button.secondary", { type: "button", onclick: () => go(weekHash(week.next_week, selectedPatient)) }, "Next week →")),
    h("p.muted", {}, `Times are ${zone} time (the clinic's clock).`));
  const bookings = week.bookings;
  const conflicts = overlapping(bookings.filter((b) => b.status !== "cancelled"));
  const today = clinicNow(zone).date;
  const days = h("div.week");
  for (let i = 0; i < 7; i += 1) {
    const day = addDays(monday, i);
    days.append(h(`section.day${day === today ? ".today" : ""}`, { dataset: { day }, "aria-label": longDate(day, { weekday: "long", day: "numeric", month: "long", year: "numeric" }) },
      h("h3", {}, longDate(day, { weekday: "long", day: "numeric", month: "short" })),
      bookings.filter((b) => wallDate(b.start_local) === day).map((b) => bookingCard(b, conflicts.has(b.id)))));
  }
  enableDragToMove(days, bookings);
  main.append(days, bookingForm(patients, selectedPatient, zone), calendarPanel());
}

function bookingCard(booking, inConflict) {
  if (booking.in_care === false) {
    // Another care team's patient: the week shows only that the robot and the therapist are busy.
    return h(`div.booking.busy.${booking.status}`, { dataset: { bookingId: String(booking.id) }, title: "Not a patient in your care" },
      h("strong", {}, `${wallTime(booking.start_local)}–${wallTime(booking.end_local)}`), h("br"), "Busy (another care team)",
      h("br"), `${booking.robot} · ${booking.status}`);
  }
  const movable = booking.status === "scheduled" && !booking.run_count; // started, finished or cancelled ones stay put
  return h(`button.booking.${booking.status}${inConflict ? ".conflict" : ""}`, {
    type: "button", onclick: () => editBooking(booking), draggable: movable ? "true" : undefined,
    dataset: { bookingId: String(booking.id) },
    title: movable ? "Drag to another day or time to move (or Alt + arrow keys: ±1 day, ±15 min)" : undefined,
  },
  h("strong", {}, `${wallTime(booking.start_local)}–${wallTime(booking.end_local)}`), h("br"), booking.patient_name,
  h("br"), `${booking.robot} · ${booking.status}${inConflict ? " · CONFLICT" : ""}`);
}

// --- drag to move (issue 16 §8) --------------------------------------------------------------------
// A day column's height stands for the clinic's working day in quarter hours: where a booking is dropped
// picks the wall time (the hint shows it while dragging); dropped onto another booking it takes that
// booking's start. The move keeps the duration; the service decides (409 conflict, 422 DST gap) and a
// refusal is shown next to the booking, which stays where it was.
const DROP_DAY_FIRST_MIN = 6 * 60;
const DROP_DAY_LAST_MIN = 22 * 60;
const STEP_MIN = 15;
const pad2 = (n) => String(n).padStart(2, "0");
const clockOf = (minutes) => `${pad2(Math.floor(minutes / 60))}:${pad2(minutes % 60)}`;

function dropWallTime(column, event, bookings) {
  const onBooking = event.target.closest && event.target.closest(".booking");
  if (onBooking) {
    const other = bookings.find((b) => String(b.id) === onBooking.dataset.bookingId);
    if (other) return wallInput(other.start_local);
  }
  const box = column.getBoundingClientRect();
  const top = box.top + column.querySelector("h3").offsetHeight;
  const fraction = Math.min(1, Math.max(0, (event.clientY - top) / Math.max(1, box.bottom - top)));
  const span = DROP_DAY_LAST_MIN - DROP_DAY_FIRST_MIN - STEP_MIN;
  const minutes = DROP_DAY_FIRST_MIN + Math.round((fraction * span) / STEP_MIN) * STEP_MIN;
  return `${column.dataset.day}T${clockOf(minutes)}`;
}

// Wall-clock arithmetic on "YYYY-MM-DDTHH:MM" as if it were UTC: the naive clinic time moves, the service
// then reads it in the clinic's zone (and refuses a time that does not exist there).
function shiftWall(wall, minutes) {
  return new Date(Date.parse(`${wall}:00Z`) + minutes * 60000).toISOString().slice(0, 16);
}

function enableDragToMove(days, bookings) {
  const byId = (id) => bookings.find((b) => String(b.id) === String(id));
  let dragged = null;
  days.addEventListener("dragstart", (event) => {
    const card = event.target.closest(".booking[draggable]");
    if (!card) return;
    dragged = byId(card.dataset.bookingId);
    event.dataTransfer.setData("text/plain", card.dataset.bookingId);
    event.dataTransfer.effectAllowed = "move";
  });
  days.addEventListener("dragend", () => { dragged = null; days.querySelectorAll(".drop-hint").forEach((el) => el.remove()); });
  for (const column of days.querySelectorAll("section.day")) {
    column.addEventListener("dragover", (event) => {
      if (!dragged) return;
      event.preventDefault();
      const wall = dropWallTime(column, event, bookings);
      days.querySelectorAll(".drop-hint").forEach((el) => { if (el.parentElement !== column) el.remove(); });
      const hint = column.querySelector(".drop-hint") || column.appendChild(h("div.drop-hint", { "aria-hidden": "true" }));
      hint.textContent = `Move to ${wallTime(wall)}`;
    });
    column.addEventListener("drop", (event) => {
      if (!dragged) return;
      event.preventDefault();
      const booking = dragged;
      const wall = dropWallTime(column, event, bookings);
      days.querySelectorAll(".drop-hint").forEach((el) => el.remove());
      if (wall !== wallInput(booking.start_local)) moveBooking(days, booking, wall);
    });
  }
  // The keyboard equivalent: Alt + ←/→ moves a day, Alt + ↑/↓ a quarter hour.
  const keySteps = { ArrowLeft: -1440, ArrowRight: 1440, ArrowUp: -STEP_MIN, ArrowDown: STEP_MIN };
  days.addEventListener("keydown", (event) => {
    const card = event.target.closest(".booking[draggable]");
    if (!card || !event.altKey || !(event.key in keySteps)) return;
    event.preventDefault();
    const booking = byId(card.dataset.bookingId);
    moveBooking(days, booking, shiftWall(wallInput(booking.start_local), keySteps[event.key]));
  });
}

async function moveBooking(days, booking, wall) {
  days.querySelectorAll(".move-error").forEach((el) => el.remove());
  const card = days.querySelector(`.booking[data-booking-id="${booking.id}"]`);
  card.classList.remove("invalid");
  const target = `${longDate(wallDate(wall), { weekday: "short", day: "numeric", month: "short" })} ${wallTime(wall)}`;
  try {
    await patch(`/sessions/${booking.id}`, { start_local: wall });
    banner("info", `Session ${booking.id} moved to ${target} (${booking.timezone} time).`);
    window.dispatchEvent(new HashChangeEvent("hashchange"));
  } catch (error) {
    card.classList.add("invalid");
    card.after(h("div.field-error.move-error", { role: "alert" }, `Could not move to ${target}. ${errorText(error)}`));
  }
}

// A calendar app cannot log in: each therapist gets a secret subscription link of their own feed,
// shown once when issued; issuing a new one or revoking ends the old one. Loaded when opened, so that
// the week itself stays one request.
function calendarPanel() {
  const output = h("div", { "aria-live": "polite" });
  const panel = h("details.panel", {}, h("summary", {}, "Calendar subscription"), output);
  let loaded = false;
  panel.addEventListener("toggle", () => {
    if (panel.open && !loaded) { loaded = true; fillCalendarPanel(output).catch(showError); }
  });
  return panel;
}

async function fillCalendarPanel(output) {
  const me = await get("/auth/me");
  const path = `/therapists/${me.id}/calendar-subscription`;
  const status = await get(path);
  const message = h("p", {}, status.issued_at
    ? `A link was issued on ${status.issued_at.slice(0, 10)}; it is shown only once. Issue a new one if it is lost.`
    : "No subscription link yet.");
  const revokeButton = h("button.secondary", { type: "button", disabled: !status.issued_at }, "Revoke link");
  const issue = async () => {
    try {
      const issued = await post(path);
      clear(message).append("Your calendar link (copy it now: it is not shown again): ",
        h("input.calendar-link", { type: "text", readonly: true, value: issued.url, "aria-label": "Calendar subscription link", onfocus: (e) => e.target.select() }));
      revokeButton.disabled = false;
    } catch (error) { showError(error); }
  };
  revokeButton.addEventListener("click", async () => {
    try { await request("DELETE", path); clear(message).append("The link is revoked: calendars using it stop updating."); revokeButton.disabled = true; } catch (error) { showError(error); }
  });
  clear(output).append(
    h("p.muted", {}, "Your own sessions in a calendar app, in the clinic's time zone, with record numbers and no names."),
    message,
    h("div.row", {}, h("button.secondary", { type: "button", onclick: issue }, status.issued_at ? "Issue a new link" : "Get calendar link"), revokeButton));
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

// Refusals next to their field (a 409 conflict goes to the start time).
function placeErrors(form, error) {
  const errors = error.status === 422 ? error.fieldErrors : error.status === 409 ? { start: error.message } : {};
  if (errors.start_local && !errors.start) errors.start = errors.start_local;
  if (errors.recurrence && !errors.start) errors.start = errors.recurrence;
  if (errors.duration_s) errors.duration_s = errors.duration_s.replace(/(\d+)/g, (m) => `${m} s`);
  const unplaced = showFieldErrors(form, errors);
  if (!Object.keys(errors).length || unplaced.length) showError(error, "form");
}

function bookingForm(patients, selectedPatient, zone) {
  const patient = h("select", { "data-field": "patient_id" }, patients.map((p) => h("option", { value: p.id, selected: String(p.id) === selectedPatient }, `${p.name} (${p.identifier})`)));
  const prescription = h("select", { "data-field": "prescription_id" });
  const start = h("input", { type: "datetime-local", "data-field": "start", value: nextQuarterHourInput(zone) });
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
        start_local: start.value, duration_s: Math.round(Number(duration.value) * 60),
      };
      if (repeat.value) body.recurrence = { frequency: repeat.value, interval: 1, count: Number(count.value) };
      try {
        const created = await post("/sessions", body);
        banner("info", `${created.length} session(s) booked.`);
        go(weekHash(wallDate(created[0].start_local), patient.value, { booked: String(created[0].id) }));
      } catch (error) {
        placeErrors(form, error);
      }
    },
  },
  h("h2", {}, "Book a session"),
  h("div.form-grid", {}, field("Patient", patient), field("Prescription", prescription), field("Start", start, { unit: zone }),
    field("Duration", duration, { unit: "min" }), field("Robot", robot), field("Repeat", repeat), field("Occurrences", count, { unit: "sessions" })),
  h("button.primary", { type: "submit" }, "Book session"));
  return form;
}

async function editBooking(booking) {
  const dialog = h("dialog", { "aria-labelledby": "booking-title" });
  // The robot builds and checks the plan ahead; asking for the booking queues it if it is not yet.
  const planState = h("span#booking-plan-state", { role: "status" }, "asking the robot…");
  const start = h("input", { type: "datetime-local", value: wallInput(booking.start_local), "data-field": "start" });
  const duration = h("input", { type: "number", min: "1", max: "240", value: String(booking.duration_s / 60), "data-field": "duration_s" });
  const when = `${longDate(wallDate(booking.start_local), { weekday: "short", day: "numeric", month: "short", year: "numeric" })} ${wallTime(booking.start_local)}`;
  const form = h("form", { method: "dialog", novalidate: true },
    h("h2#booking-title", {}, `Session ${booking.id}: ${booking.patient_name}`),
    h("p", {}, `${when} (${booking.timezone}) on ${booking.robot}, ${booking.status}.`),
    booking.status === "cancelled" ? null : h("p", {}, h("strong", {}, "Motion plan: "), planState),
    field("Move to", start, { unit: booking.timezone }), field("Duration", duration, { unit: "min" }),
    h("div.dialog-buttons", {},
      h("a.button", { href: `#/session/${booking.id}`, onclick: () => dialog.close() }, "Open session console"),
      booking.status === "scheduled" ? h("button.danger", { type: "button", onclick: () => save({ status: "cancelled" }) }, "Cancel session") : null,
      h("button.secondary", { type: "button", onclick: () => dialog.close() }, "Close"),
      h("button.primary", { type: "button", onclick: () => save({ start_local: start.value, duration_s: Math.round(Number(duration.value) * 60) }) }, "Move")));
  async function save(change) {
    try {
      await patch(`/sessions/${booking.id}`, change);
      dialog.close();
      banner("info", change.status === "cancelled" ? "Session cancelled." : "Session moved.");
      window.dispatchEvent(new HashChangeEvent("hashchange"));
    } catch (error) {
      placeErrors(form, error);
    }
  }
  dialog.append(form);
  document.body.append(dialog);
  let stopFollowing = () => {};
  if (booking.status !== "cancelled") {
    get(`/sessions/${booking.id}`).then((b) => { if (dialog.open) stopFollowing = followPlan(booking.id, planState, b.plan); })
      .catch(() => { planState.textContent = planWords(null); });
  }
  dialog.addEventListener("close", () => { stopFollowing(); dialog.remove(); });
  openDialog(dialog);
}
