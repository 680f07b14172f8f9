// The REST API under /api/v1 (issue 6). Authentication is the HttpOnly session cookie set at login,
// so no token is ever kept in script-readable storage.
export const API = "/api/v1";
export const CSRF_HEADER = "X-Requested-With";

export class ApiError extends Error {
  constructor(status, detail, body = {}) {
    super(describeDetail(detail) || `HTTP ${status}`);
    this.status = status;
    this.detail = detail;
    this.fieldErrors = fieldErrors(detail);
    this.fieldItems = fieldItems(detail);
    // 412: someone changed the record since this page read it (docs/service.md, optimistic concurrency).
    this.conflict = status === 412
      ? { currentVersion: body.current_version ?? null, changedBy: body.changed_by ?? null, changedAt: body.changed_at ?? null }
      : null;
  }
}

// The version a change is based on, as the server's ETag writes it (If-Match).
export const ifMatch = (version) => `"${version}"`;

// FastAPI 422 bodies: {detail: [{loc: ["body", "segments", 0, "cue", ...], msg}]} -> {"segments[0].cue": msg}
export function fieldErrors(detail) {
  const errors = {};
  if (!Array.isArray(detail)) return errors;
  for (const item of detail) {
    const loc = (item.loc || []).filter((part) => part !== "body" && part !== "query" && part !== "path");
    let name = "";
    for (const part of loc) name += typeof part === "number" ? `[${part}]` : (name ? "." : "") + part;
    errors[name || "_"] = item.msg;
  }
  return errors;
}

// The same refusals with their structured parts (path, type, input value, ctx limits) for the translation
// into the screen's units and numbering (js/language.js).
export function fieldItems(detail) {
  const items = {};
  for (const [name, msg] of Object.entries(fieldErrors(detail))) items[name] = { path: name, msg };
  if (!Array.isArray(detail)) return items;
  for (const item of detail) {
    const name = Object.keys(fieldErrors([item]))[0];
    items[name] = { path: name, msg: item.msg, type: item.type, input: item.input, ctx: item.ctx };
  }
  return items;
}

function describeDetail(detail) {
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail.map((d) => {
      const loc = (d.loc || []).filter((p) => p !== "body").join(".");
      return loc ? `${loc}: ${d.msg}` : d.msg;
    }).join("; ");
  }
  return detail ? JSON.stringify(detail) : "";
}

export async function request(method, path, body, { raw = false, version } = {}) {
  // The custom header proves the request comes from the console's own pages (CSRF check, docs/service.md).
  const options = { method, credentials: "same-origin", headers: { [CSRF_HEADER]: "ssp-rehab" } };
  // A change of a versioned record (patient, prescription) names the version it was based on.
  if (version !== undefined) options.headers["If-Match"] = ifMatch(version);
  if (body !== undefined) {
    options.headers["Content-Type"] = "application/json";
    options.body = JSON.stringify(body);
  }
  let response;
  try {
    response = await fetch(API + path, options);
  } catch (error) {
    throw new ApiError(0, "the console service does not answer (network error)");
  }
  if (!response.ok) {
    let detail = response.statusText;
    let answer = {};
    try { answer = await response.json(); detail = answer.detail; } catch (_) { /* not JSON */ }
    const error = new ApiError(response.status, detail, answer || {});
    if (response.status === 401) window.dispatchEvent(new CustomEvent("ssp:unauthorised"));
    throw error;
  }
  if (raw) return response;
  if (response.status === 204) return null;
  return response.json();
}

export const get = (path) => request("GET", path);
export const post = (path, body) => request("POST", path, body);
export const patch = (path, body, options) => request("PATCH", path, body, options);
export const put = (path, body, options) => request("PUT", path, body, options);
export const del = (path) => request("DELETE", path);

export function query(params) {
  const search = new URLSearchParams();
  for (const [key, value] of Object.entries(params)) {
    if (value !== undefined && value !== null && value !== "") search.set(key, value);
  }
  const text = search.toString();
  return text ? `?${text}` : "";
}
