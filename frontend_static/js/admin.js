// Administration (admins only; the API refuses others): accounts and the audit log (issue 16, build §7).
import { get, patch, post, query } from "./api.js";
import { exportControl } from "./exports.js";
import { words } from "./language.js";
import { badge, banner, clear, clearErrors, confirmDialog, field, fmtDateTime, h, openDialog, showError, showFieldErrors, table } from "./ui.js";

const ROLES = ["therapist", "admin"];
const AUDIT_PAGE = 100;

// The bulk export of pseudonymised runs for a study, with its progress (issue 20 Build 7).
function studyExportForm() {
  const today = new Date().toISOString().slice(0, 10);
  const from = h("input", { type: "date", value: today, required: true });
  const to = h("input", { type: "date", value: today, required: true });
  const diagnosis = h("input", { type: "text", maxlength: 200, placeholder: "any" });
  const layout = h("select", {}, h("option", { value: "folders" }, "A folder per run (CSV, Parquet, JSON, C3D)"),
    h("option", { value: "parquet_dataset" }, "Parquet dataset (DuckDB, pandas)"));
  const freeText = h("input", { type: "checkbox" });
  const start = () => `/exports/bulk/jobs${query({ from_date: from.value, to_date: to.value, diagnosis: diagnosis.value, layout: layout.value, include_free_text: freeText.checked || undefined })}`;
  return h("div.panel#study-export", {},
    h("div.row", {}, field("From (UTC day)", from), field("To (UTC day)", to), field("Diagnosis", diagnosis), field("Layout", layout)),
    h("label", {}, freeText, " Keep free-text diagnosis and notes (may identify people)"),
    h("div.row", {}, exportControl("Export the study", start)));
}

export async function adminPage(main, user) {
  if (!user || user.role !== "admin") {
    main.append(h("h1", {}, "Administration"), h("p", {}, "Only an administrator can manage accounts and read the audit log."));
    return;
  }
  const usersHost = h("div#users");
  const auditHost = h("div#audit");
  main.append(h("h1", {}, "Administration"), h("h2", {}, "Accounts"), usersHost, newUserForm(() => loadUsers()),
    h("h2", {}, "Study export"), studyExportForm(), h("h2", {}, "Audit log"), auditHost);
  let names = {};
  async function loadUsers() {
    const users = await get("/users?limit=500");
    names = Object.fromEntries(users.map((u) => [u.id, u.full_name || u.username]));
    clear(usersHost).append(table(["User name", "Full name", "Role", "State", "Created", ""], users.map((u) => h("tr", { dataset: { user: u.username } },
      h("td", {}, u.username), h("td", {}, u.full_name || "—"), h("td", {}, u.role), h("td", {}, badge(u.is_active ? "active" : "deactivated")),
      h("td", {}, fmtDateTime(u.created_at)),
      h("td", {}, u.id === user.id ? h("span.muted", {}, "you") : h("div.row", {},
        h("button.secondary", { type: "button", onclick: () => change(u, { role: u.role === "admin" ? "therapist" : "admin" }, `Make ${u.username} ${u.role === "admin" ? "a therapist" : "an admin"}?`) },
          u.role === "admin" ? "Make therapist" : "Make admin"),
        h("button.secondary", { type: "button", onclick: () => change(u, { is_active: !u.is_active }, `${u.is_active ? "Deactivate" : "Reactivate"} ${u.username}?`) },
          u.is_active ? "Deactivate" : "Reactivate"),
        h("button.secondary", { type: "button", onclick: () => newPassword(u) }, "Set a new password")))))));
  }
  async function change(account, body, question) {
    if (!(await confirmDialog({ title: question, body: "The change is recorded in the audit log.", ok: "Change" }))) return;
    try { await patch(`/users/${account.id}`, body); clearErrors("form"); banner("info", `${account.username} changed.`); await loadUsers(); } catch (error) { showError(error, "form"); }
  }
  async function newPassword(account) {
    const input = h("input", { type: "password", autocomplete: "new-password", "data-field": "password" });
    const dialog = h("dialog", { "aria-labelledby": "password-title" });
    const form = h("form", { method: "dialog", novalidate: true, onsubmit: async (event) => {
      event.preventDefault();
      try { await patch(`/users/${account.id}`, { password: input.value }); dialog.close(); banner("info", `New password set for ${account.username}.`); } catch (error) {
        if (error.status === 422) showFieldErrors(form, error.fieldItems); else showError(error, "form");
      }
    } }, h("h2#password-title", {}, `New password for ${account.username}`), field("New password", input),
    h("div.dialog-buttons", {}, h("button.secondary", { type: "button", onclick: () => dialog.close() }, "Cancel"), h("button.primary", { type: "submit" }, "Set password")));
    dialog.append(form);
    document.body.append(dialog);
    dialog.addEventListener("close", () => dialog.remove());
    openDialog(dialog, input);
  }

  // The audit log, newest first, filtered by kind of record and user, a page at a time.
  const kind = h("select", { "aria-label": "Kind of record" }, ["", "patient", "prescription", "scheduled_session", "session_run", "run_notes", "user", "robot"]
    .map((k) => h("option", { value: k }, k ? words(k) : "all records")));
  const who = h("select", { "aria-label": "User" });
  let offset = 0;
  const entries = h("tbody");
  const more = h("button.secondary", { type: "button", onclick: () => { offset += AUDIT_PAGE; loadAudit(false).catch(showError); } }, "Older entries");
  async function loadAudit(fresh = true) {
    if (fresh) offset = 0;
    const rows = await get(`/audit${query({ resource_type: kind.value, user_id: who.value, limit: AUDIT_PAGE, offset })}`);
    if (fresh) clear(entries);
    entries.append(...rows.map((e) => h("tr", {}, h("td", {}, fmtDateTime(e.utc)), h("td", {}, names[e.user_id] || (e.user_id ? `user ${e.user_id}` : "system")),
      h("td", {}, words(e.action)), h("td", {}, `${words(e.resource_type)}${e.resource_id ? ` ${e.resource_id}` : ""}`),
      h("td.details", {}, Object.keys(e.details || {}).length ? JSON.stringify(e.details) : "—"))));
    more.hidden = rows.length < AUDIT_PAGE;
  }
  await loadUsers();
  clear(who).append(h("option", { value: "" }, "all users"), ...Object.entries(names).map(([id, name]) => h("option", { value: id }, name)));
  kind.addEventListener("change", () => loadAudit().catch(showError));
  who.addEventListener("change", () => loadAudit().catch(showError));
  auditHost.append(h("div.row", {}, field("Kind of record", kind), field("User", who)),
    table(["When", "Who", "Action", "Record", "Details"], []), more);
  auditHost.querySelector("tbody").replaceWith(entries);
  await loadAudit();
}

function newUserForm(onCreated) {
  const f = {
    username: h("input", { "data-field": "username", autocomplete: "off" }),
    full_name: h("input", { "data-field": "full_name" }),
    role: h("select", { "data-field": "role" }, ROLES.map((r) => h("option", { value: r }, r))),
    password: h("input", { type: "password", "data-field": "password", autocomplete: "new-password" }),
  };
  const form = h("form.panel", { novalidate: true, onsubmit: async (event) => {
    event.preventDefault();
    try {
      const created = await post("/users", Object.fromEntries(Object.entries(f).map(([k, el]) => [k, el.value])));
      clearErrors("form");
      showFieldErrors(form, {});
      banner("info", `Account ${created.username} created.`);
      Object.values(f).forEach((el) => { if (el.tagName === "INPUT") el.value = ""; });
      await onCreated();
    } catch (error) {
      const unplaced = error.status === 422 ? showFieldErrors(form, error.fieldItems) : [];
      if (error.status !== 422 || unplaced.length) showError(error, "form");
    }
  } }, h("h3", {}, "New account"),
  h("div.form-grid", {}, field("User name", f.username), field("Full name", f.full_name), field("Role", f.role), field("Initial password", f.password)),
  h("button.primary", { type: "submit" }, "Create account"));
  return form;
}
