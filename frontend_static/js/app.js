// Entry point: hash routing, the login state, the always-present emergency stop and the robot status.
import { get, post } from "./api.js";
import { adminPage } from "./admin.js";
import { sessionPage } from "./console.js";
import { protocolsPage } from "./protocols.js";
import { editPatientPage, historyPage, loginPage, newPatientPage, patientPage, patientsPage, prescriptionPage, schedulePage } from "./pages.js";
import { clinicClock, describeRobot, nextStepAfterReset, setClinicZone } from "./language.js";
import { banner, clear, clearBanner, clearErrors, engineeringOn, errorText, h, setEngineering } from "./ui.js";

// The software emergency stop: ONE request, no confirmation, from every page and over every dialog; the key
// is Escape, caught before anything else (also while typing in a field or with a dialog open). It goes to the
// robot's own stop listener (its address from GET /health), which no work of the web service can hold up;
// if that cannot be reached, to the web service's /api/v1/estop. Neither needs a login.
export const ESTOP_KEY = "Escape";
const estopButton = document.getElementById("estop");
const WEB_STOP = "/api/v1/estop";
let stopListener = null;
function learnStopAddress(health) { if (health && health.estop) stopListener = health.estop.url || null; }

async function sendStop() {
  if (stopListener) {
    try {
      return await fetch(stopListener, { method: "POST", mode: "cors", credentials: "include", cache: "no-store" });
    } catch (error) { /* unreachable (its robot daemon is gone, or a proxy does not forward it): the web route */ }
  }
  return fetch(WEB_STOP, { method: "POST", credentials: "same-origin", headers: { "X-Requested-With": "ssp-rehab" } });
}

async function emergencyStop() {
  estopButton.classList.add("sent");
  const at = clinicClock(new Date());
  const hardware = "Use the robot's red hardware stop button.";
  try {
    const response = await sendStop();
    const body = await response.json().catch(() => ({ detail: response.statusText }));
    if (response.ok) {
      banner("error", `EMERGENCY STOP sent at ${at}: latched by the robot. Reset it from the session console once safe.`, { key: "estop", sticky: true });
    } else if (response.status === 504) {
      banner("error", `EMERGENCY STOP requested at ${at}, NOT CONFIRMED by the robot: ${body.detail}`, { key: "estop", sticky: true });
    } else if (response.status === 503) {
      banner("error", `Emergency stop not received at ${at}: ${body.detail}. ${hardware}`, { key: "estop", sticky: true });
    } else if (response.status === 409) {
      banner("warning", `Emergency stop at ${at}: ${body.detail}.`, { key: "estop", sticky: true });
    } else {
      banner("error", `Emergency stop not delivered (HTTP ${response.status}: ${body.detail}). ${hardware}`, { key: "estop", sticky: true });
    }
  } catch (error) {
    banner("error", `Emergency stop not delivered: neither the robot nor the console service answers. ${hardware}`, { key: "estop", sticky: true });
  }
  window.dispatchEvent(new CustomEvent("ssp:estop"));
  setTimeout(() => estopButton.classList.remove("sent"), 1500);
}
estopButton.addEventListener("click", emergencyStop);
window.addEventListener("keydown", (event) => {
  if (event.key === ESTOP_KEY && !event.repeat) { event.preventDefault(); emergencyStop(); }
}, { capture: true });
// The listener's address is kept fresh (a restarted robot daemon may listen elsewhere).
const refreshStopAddress = () => get("/health").then(learnStopAddress).catch(() => null);
setInterval(refreshStopAddress, 15_000);

// --- login state -----------------------------------------------------------------------------------
let user = null;
const main = document.getElementById("main");
const nav = document.getElementById("nav");
const logout = document.getElementById("logout");
const userName = document.getElementById("user-name");
const engineeringSwitch = document.getElementById("engineering-switch");
const adminLinks = document.querySelectorAll("[data-admin]");

function setUser(next) {
  user = next;
  nav.hidden = !user;
  logout.hidden = !user;
  engineeringSwitch.closest("label").hidden = !user;
  adminLinks.forEach((link) => { link.hidden = !user || user.role !== "admin"; });
  userName.textContent = user ? `${user.full_name || user.username} (${user.role})` : "";
  userName.title = userName.textContent;
}
engineeringSwitch.checked = engineeringOn();
document.body.classList.toggle("engineering", engineeringSwitch.checked);
engineeringSwitch.addEventListener("change", () => setEngineering(engineeringSwitch.checked));
// The switch belongs to this browser (its tabs share it, and the 3D view's panel follows it per login): a change
// in another tab shows here too; that tab has told the view already.
window.addEventListener("storage", () => {
  engineeringSwitch.checked = engineeringOn();
  document.body.classList.toggle("engineering", engineeringSwitch.checked);
});
logout.addEventListener("click", async () => {
  await post("/auth/logout").catch(() => null);
  setUser(null);
  clearErrors("robot", "robot-alert", "robot-next", "fault");
  location.hash = "#/login";
});
window.addEventListener("ssp:unauthorised", () => {
  if (user) { setUser(null); banner("warning", "Your login session ended: please log in again."); }
  if (location.hash !== "#/login") location.hash = "#/login";
});

// --- robot status in the top bar: offline, faults, abnormal stops and a latched emergency stop are always
// visible, in red, with the reason and the next step in words (js/language.js) ---------------------------
const robotStatus = document.getElementById("robot-status");
let lastRobotLevel = null;
// When the state shown was taken: the 2 s poll's answer may arrive after a newer state pushed by the live
// telemetry (a stop), and must not take the page back to it (it cleared the stop's banner and showed MOVING).
let robotShownAt = 0;
function showRobot(state, takenAt = performance.now()) {
  if (takenAt < robotShownAt) return;
  robotShownAt = takenAt;
  const shown = describeRobot(state);
  robotStatus.className = `robot-status ${shown.level}`;
  robotStatus.textContent = `Robot: ${shown.label}`;
  robotStatus.dataset.stopReason = shown.stopReason;
  clearBanner("robot");
  if (shown.level === "bad") {
    clearBanner("robot-next");
    const alert = banner(shown.stopReason === "fall" ? "fall" : "error", shown.reason, { key: "robot-alert", sticky: true });
    alert.querySelector("span").append(h("span.next-step", {}, shown.next));
  } else {
    clearBanner("robot-alert");
    // Reset: the red banners go, and the next step shows while the stop waits for its acknowledgement.
    if (lastRobotLevel === "bad") clearBanner("estop");
    if (lastRobotLevel === "bad" || document.querySelector('[data-key="robot-next"]')) showNextStep();
  }
  lastRobotLevel = shown.level;
}
// After a reset: a stop that moved the patient must be acknowledged before the next start (issue 20, build 9).
async function showNextStep() {
  const pending = await get("/reviews/pending").catch(() => null);
  if (!pending) { clearBanner("robot-next"); return; }
  banner("warning", nextStepAfterReset(pending), { key: "robot-next", sticky: true });
}
window.addEventListener("ssp:acknowledged", () => showNextStep());
async function pollRobot() {
  if (!user) { robotStatus.textContent = ""; robotStatus.className = "robot-status"; return; }
  try {
    const asked = performance.now();
    showRobot(await get("/robot/state"), asked);
  } catch (error) {
    if (error.status !== 503) {
      robotStatus.className = "robot-status bad";
      robotStatus.textContent = "Robot: unknown";
      return;
    }
    // Not ready: the public health check says whether the robot daemon is still starting (with its step and
    // the seconds so far) or has failed (with the reason), never a bare "offline" for a robot warming up.
    const daemon = await get("/health").then((health) => health.robot).catch(() => null);
    showRobotDaemon(daemon, errorText(error));
  }
}
function showRobotDaemon(daemon, fallback) {
  clearBanner("robot-alert");
  if (daemon && daemon.state === "starting") {
    robotStatus.className = "robot-status warn";
    robotStatus.textContent = "Robot: STARTING";
    banner("warning", `The robot is starting: ${daemon.reason}. The console attaches by itself when it is ready.`,
      { key: "robot", sticky: true });
    return;
  }
  robotStatus.className = "robot-status bad";
  robotStatus.textContent = daemon && daemon.state === "fault" ? "Robot: FAULT" : "Robot: OFFLINE";
  const why = daemon ? `The robot did not start or stopped working: ${daemon.reason}.` : fallback;
  const alert = banner("error", why, { key: "robot", sticky: true });
  // The console re-attaches (and restarts a robot process that is gone) by itself; Retry checks again now.
  alert.querySelector("span").append(" ", h("button.retry", { type: "button", onclick: () => pollRobot() }, "Retry"));
}
window.addEventListener("ssp:robot-state", (event) => { if (user) showRobot(event.detail); });
setInterval(pollRobot, 2000);

// --- routing ---------------------------------------------------------------------------------------
const ROUTES = [
  [/^#\/login$/, () => loginPage(main, { onLogin: (u) => { setUser(u); pollRobot(); location.hash = "#/patients"; } })],
  [/^#\/patients$/, () => patientsPage(main)],
  [/^#\/patients\/new$/, () => newPatientPage(main)],
  [/^#\/patients\/(\d+)$/, (m) => patientPage(main, Number(m[1]))],
  [/^#\/patients\/(\d+)\/edit$/, (m) => editPatientPage(main, Number(m[1]))],
  [/^#\/prescriptions\/new$/, (m, params) => prescriptionPage(main, null, params)],
  [/^#\/prescriptions\/(\d+)$/, (m, params) => prescriptionPage(main, Number(m[1]), params)],
  [/^#\/schedule$/, (m, params) => schedulePage(main, params)],
  [/^#\/session\/(\d+)$/, (m, params, cleanup) => sessionPage(main, Number(m[1]), cleanup)],
  [/^#\/history$/, (m, params) => historyPage(main, params)],
  [/^#\/admin$/, () => adminPage(main, user)],
  [/^#\/protocols$/, (m, params) => protocolsPage(main, params)],
];
let cleanup = [];
// The clinic's zone, for every date and time shown (public, like the rest of GET /health).
const clinicZoneKnown = get("/health").then((health) => { learnStopAddress(health); setClinicZone(health.clinic_timezone); }).catch(() => null);

async function route() {
  await clinicZoneKnown;
  cleanup.forEach((fn) => fn());
  cleanup = [];
  // A dialog belongs to the page that opened it; form and command errors too.
  document.querySelectorAll("dialog[open]").forEach((dialog) => dialog.close());
  clearErrors("form", "command", "login");
  const [path, search] = (location.hash || "#/patients").split("?");
  const params = new URLSearchParams(search || "");
  if (!user && path !== "#/login") {
    try { setUser(await get("/auth/me")); } catch (_) { location.hash = "#/login"; return; }
  }
  clear(main);
  const onLogin = path === "#/login";
  nav.hidden = !user || onLogin;
  logout.hidden = !user || onLogin;
  document.querySelectorAll("nav a").forEach((a) => a.classList.toggle("active", path.startsWith(a.getAttribute("href"))));
  for (const [pattern, render] of ROUTES) {
    const match = path.match(pattern);
    if (!match) continue;
    try {
      await render(match, params, cleanup);
    } catch (error) {
      if (error.status !== 401) main.append(h("div.banner.error", { role: "alert" }, errorText(error)));
    }
    main.focus({ preventScroll: true });
    return;
  }
  main.append(h("p", {}, "Page not found. ", h("a", { href: "#/patients" }, "Go to patients")));
}
window.addEventListener("hashchange", route);
route().then(pollRobot);
