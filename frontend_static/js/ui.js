// DOM helpers, banners, the confirmation dialog and unit formatting shared by every page.
import { clinicClock, clinicDateTime, conflictWords, fieldMessage, localTimes } from "./language.js";

// h("tag.class#id", {attrs}, ...children): a small element builder (text children are escaped by the DOM).
export function h(spec, attrs = {}, ...children) {
  // "tag.class#id" or "tag#id.class": the tag first, then any mix of .classes and one #id.
  const tag = spec.match(/^[a-z0-9]*/i)[0];
  const classes = [...spec.matchAll(/\.([\w-]+)/g)].map((m) => m[1]);
  const id = (spec.match(/#([\w-]+)/) || [])[1];
  const el = document.createElement(tag || "div");
  if (classes.length) el.className = classes.join(" ");
  if (id) el.id = id;
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === undefined || value === null || value === false) continue;
    if (key.startsWith("on")) el.addEventListener(key.slice(2), value);
    else if (key === "dataset") Object.assign(el.dataset, value);
    else if (key === "text") el.textContent = value;
    else if (value === true) el.setAttribute(key, "");
    else el.setAttribute(key, value);
  }
  for (const child of children.flat()) {
    if (child === undefined || child === null || child === false) continue;
    el.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return el;
}

export function clear(el) { while (el.firstChild) el.removeChild(el.firstChild); return el; }

// --- numbers with units (SI inside, mm and degrees at this edge) ---
export const M_TO_MM = 1000;
export const RAD_TO_DEG = 180 / Math.PI;
export function fmt(value, unit, digits = 1) {
  if (value === null || value === undefined || !Number.isFinite(Number(value))) return `— ${unit}`;
  return `${Number(value).toFixed(digits)} ${unit}`;
}
export function fmtDateTime(iso) {
  if (!iso) return "—";
  return clinicDateTime(new Date(iso), { weekday: "short", year: "numeric", month: "short", day: "numeric", hour: "2-digit", minute: "2-digit" });
}
export function fmtTime(iso) {
  return clinicClock(new Date(iso), { hour: "2-digit", minute: "2-digit" });
}
export function badge(state) { return h(`span.badge.${String(state).replace(/[^a-z_]/gi, "")}`, {}, String(state).replace(/_/g, " ")); }

// --- banners ---
const bannerHost = () => document.getElementById("banners");
export function banner(kind, message, { key, sticky = false } = {}) {
  const host = bannerHost();
  if (key) host.querySelectorAll(`[data-key="${key}"]`).forEach((el) => el.remove());
  const el = h(`div.banner.${kind}`, { role: kind === "error" || kind === "fall" ? "alert" : "status", dataset: key ? { key } : {} },
    h("span", {}, message),
    h("button", { type: "button", onclick: () => el.remove(), "aria-label": "Dismiss message" }, "Dismiss"));
  host.append(el);
  if (!sticky && kind !== "error" && kind !== "fall") setTimeout(() => el.remove(), 8000);
  return el;
}
export function clearBanner(key) { bannerHost().querySelectorAll(`[data-key="${key}"]`).forEach((el) => el.remove()); }
// Error banners of a form or an action carry a key: the next success of the same thing removes them.
export function clearErrors(...keys) { keys.forEach(clearBanner); }
export function showError(error, key) { return banner("error", errorText(error), { key }); }
export function errorText(error) {
  if (error && error.conflict) return conflictText(error.conflict);
  if (error && error.status === 503) return `Robot offline: ${error.message}`;
  if (error && error.status === 409) return `Not possible now: ${conflictWords(error.message)}`;
  if (error && error.status === 422) {
    const items = Object.values(error.fieldItems || {});
    return `Please check: ${items.map((item) => fieldMessage(item)).join(" ") || error.message}`;
  }
  return `Error: ${error && error.message ? error.message : error}`;
}

// 412: "Changed by X at HH:MM (now version N): not saved. Reload …" in the clinic's time as the page shows it.
export function conflictText({ changedBy, changedAt, currentVersion }) {
  const when = changedAt ? fmtTime(changedAt) : null;
  const who = changedBy || "someone else";
  return `Changed by ${who}${when ? ` at ${when}` : ""}${currentVersion ? ` (now version ${currentVersion})` : ""}` +
    ": your change was not saved. Reload the page to see theirs, then make your change again.";
}

// What the screen shows of an input's value: its label, unit and the factor from the API's SI value.
function fieldMeta(input) {
  const label = input.dataset.label || (input.labels && input.labels[0] ? input.labels[0].textContent : "");
  return { label, unit: input.dataset.unit || "", scale: Number(input.dataset.scale || 1) };
}

// Shows API field errors (422) next to the inputs whose data-field matches the error's field path, in the
// input's own label, unit and numbering (js/language.js); `errors` maps a path to a structured refusal
// (ApiError.fieldItems) or to a message already in words.
export function showFieldErrors(form, errors) {
  form.querySelectorAll(".field-error").forEach((el) => el.remove());
  form.querySelectorAll(".invalid").forEach((el) => el.classList.remove("invalid"));
  let first = null;
  const unplaced = [];
  for (const [name, error] of Object.entries(errors)) {
    const input = findField(form, name);
    const words = (meta) => (typeof error === "string" ? localTimes(error) : fieldMessage({ path: name, ...error }, meta));
    if (!input) { unplaced.push(words({})); continue; }
    const message = words(fieldMeta(input));
    input.classList.add("invalid");
    input.setAttribute("aria-invalid", "true");
    const note = h("div.field-error", { role: "alert" }, message);
    (input.closest(".field") || input.parentElement).append(note);
    first = first || input;
  }
  if (first) first.focus();
  return unplaced;
}
function findField(form, name) {
  // The most specific match: "segments[0].cue.amplitude_m_s2", else a parent path such as "segments[0].cue".
  let path = name;
  while (path) {
    const input = form.querySelector(`[data-field="${CSS.escape(path)}"]`);
    if (input) return input;
    const cut = Math.max(path.lastIndexOf("."), path.lastIndexOf("["));
    path = cut > 0 ? path.slice(0, cut) : "";
  }
  return null;
}

// --- confirmation dialog: resolves true only on the explicit OK button ---
export function confirmDialog({ title, body, ok, checklist = [] }) {
  const dialog = document.getElementById("confirm-dialog");
  document.getElementById("confirm-title").textContent = title;
  const okButton = document.getElementById("confirm-ok");
  okButton.textContent = ok;
  const bodyHost = clear(document.getElementById("confirm-body"));
  bodyHost.append(h("p", {}, body));
  const boxes = checklist.map((text, i) => h("input", { type: "checkbox", id: `confirm-check-${i}` }));
  if (checklist.length) {
    bodyHost.append(h("div.checklist", {}, checklist.map((text, i) => h("label", { for: `confirm-check-${i}` }, boxes[i], text))));
  }
  const sync = () => { okButton.disabled = !boxes.every((b) => b.checked); };
  boxes.forEach((b) => b.addEventListener("change", sync));
  sync();
  return new Promise((resolve) => {
    dialog.returnValue = "";
    dialog.addEventListener("close", () => resolve(dialog.returnValue === "ok"), { once: true });
    openDialog(dialog, boxes[0] || okButton);
  });
}

// --- dialogs, never modal in the browser's sense (issue 20). A showModal() dialog sits in the top layer and
// makes the rest of the page inert, the emergency stop included: the red button was dimmed, covered and out of
// Tab's reach. Dialogs open with show() over a backdrop of our own; the page behind them is made inert here,
// all but the emergency stop, the robot's status and the banners, and the top bar stays above the backdrop.
const openDialogs = new Set();
let dialogBackdrop = null;
let topBarWatch = null;
export function openDialog(dialog, focusTarget) {
  const returnTo = document.activeElement;
  openDialogs.add(dialog);
  dialog.show();
  layOutDialogs();
  dialog.addEventListener("close", () => {
    openDialogs.delete(dialog);
    layOutDialogs();
    if (!openDialogs.size && returnTo && returnTo.isConnected) returnTo.focus({ preventScroll: true });
  }, { once: true });
  const first = focusTarget || dialog.querySelector("input, select, textarea, button, a[href]");
  if (first) first.focus();
}
function layOutDialogs() {
  const open = openDialogs.size > 0;
  document.body.classList.toggle("dialog-open", open);
  const behind = [document.getElementById("main"), ...document.querySelectorAll(".topbar > :not(#estop):not(#robot-status)")];
  behind.forEach((el) => { el.inert = open; });
  if (open && !dialogBackdrop) document.body.append(dialogBackdrop = h("div.dialog-backdrop"));
  if (!open && dialogBackdrop) { dialogBackdrop.remove(); dialogBackdrop = null; }
  const top = document.querySelector(".sticky-top");
  const place = () => document.documentElement.style.setProperty("--dialog-top", `${Math.round(top.getBoundingClientRect().bottom)}px`);
  if (open && !topBarWatch) { place(); topBarWatch = new ResizeObserver(place); topBarWatch.observe(top); }
  if (!open && topBarWatch) { topBarWatch.disconnect(); topBarWatch = null; }
}

export function field(labelText, input, { unit, hint, id } = {}) {
  const inputId = id || input.id || `f-${Math.random().toString(36).slice(2, 9)}`;
  input.id = inputId;
  if (!input.dataset.label) input.dataset.label = labelText;
  if (unit && !input.dataset.unit) input.dataset.unit = unit;
  return h("div.field", {},
    h("label", { for: inputId }, labelText),
    unit ? h("div.unit-input", {}, input, h("span.unit", {}, unit)) : input,
    hint ? h("div.hint", {}, hint) : null);
}

export function table(headers, rows, { caption } = {}) {
  return h("table", {},
    caption ? h("caption.muted", {}, caption) : null,
    h("thead", {}, h("tr", {}, headers.map((x) => (typeof x === "string" ? h("th", { scope: "col" }, x) : x)))),
    h("tbody", {}, rows));
}

// --- the "engineering" switch: tick timing, deadline misses, drive internals and viser's own controls are
// for technicians; clinicians see them only on request (the choice is kept in this browser).
const ENGINEERING_KEY = "ssp-rehab.engineering";
export function engineeringOn() { return localStorage.getItem(ENGINEERING_KEY) === "on"; }
export function setEngineering(on) {
  localStorage.setItem(ENGINEERING_KEY, on ? "on" : "off");
  document.body.classList.toggle("engineering", on);
  window.dispatchEvent(new CustomEvent("ssp:engineering", { detail: on }));
}
