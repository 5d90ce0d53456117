// The JSON API of docs/console.md ("API"). Every call goes through request(): a 401 anywhere
// tells the console to show the login page; other errors become ApiError with the server's
// {"error": {"code", "message"}}.

export class ApiError extends Error {
  constructor(status, code, message) {
    super(message);
    this.status = status;
    this.code = code;
  }
}

const listeners = new Set();

/** Call ``fn()`` whenever the API answers 401 (the session is missing or expired). */
export function onUnauthorized(fn) {
  listeners.add(fn);
}

async function errorFrom(response) {
  let code = `HTTP_${response.status}`;
  let message = response.statusText || "request failed";
  try {
    const body = await response.json();
    if (body && typeof body.error === "object" && body.error !== null) {
      code = String(body.error.code ?? code);
      message = String(body.error.message ?? message);
    }
  } catch {
    // Not JSON (a proxy's page, a dropped connection): keep the status line.
  }
  return new ApiError(response.status, code, message);
}

/** fetch() an API path; resolves to the Response when it is 2xx, else throws ApiError.
 * A request that changes something carries X-Cellvision: console, the server's proof that
 * this page sent it and not another site's (docs/console.md, "Security"). */
export async function request(path, init = {}) {
  const method = (init.method || "GET").toUpperCase();
  const headers = { ...(init.headers || {}) };
  if (method !== "GET" && method !== "HEAD") headers["X-Cellvision"] = "console";
  let response;
  try {
    response = await fetch(path, { credentials: "same-origin", cache: "no-store", ...init, headers });
  } catch (exc) {
    throw new ApiError(0, "UNREACHABLE", `the server does not answer (${exc.message})`);
  }
  if (response.status === 401 && path !== "/api/login") {
    for (const fn of listeners) fn();
  }
  if (!response.ok) throw await errorFrom(response);
  return response;
}

export async function getJson(path) {
  return (await request(path)).json();
}

export async function postJson(path, body) {
  const response = await request(path, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(body),
  });
  return response.json();
}

/** A query string from the non-empty entries of ``params``. */
export function query(params) {
  const search = new URLSearchParams();
  for (const [key, value] of Object.entries(params)) {
    if (value === null || value === undefined || value === "") continue;
    search.set(key, String(value));
  }
  const text = search.toString();
  return text ? `?${text}` : "";
}

export const api = {
  server: () => getJson("/api/server"),
  cameras: () => getJson("/api/cameras"),
  frameUrl: (name, tick) => `/api/cameras/${encodeURIComponent(name)}/frame.jpg?t=${tick}`,
  inspections: () => getJson("/api/inspections"),
  /** Sign in: a token (a role's, or a badge) as a string, or {user, pin}. */
  login: (credentials) =>
    postJson("/api/login", typeof credentials === "string" ? { token: credentials } : credentials),
  logout: () => postJson("/api/logout", {}),
  /**
   * Try an inspection. ``request`` is {source, result_id?, options, overlay}; ``file`` a File or
   * Blob for source "upload".
   */
  async tryInspection(name, requestBody, file, signal) {
    const form = new FormData();
    form.append("request", new Blob([JSON.stringify(requestBody)], { type: "application/json" }));
    if (file) form.append("image", file, file.name || "upload");
    const response = await request(`/api/inspections/${encodeURIComponent(name)}/try`, {
      method: "POST",
      body: form,
      signal,
    });
    return response.json();
  },
  save: (name, options, why) =>
    postJson(`/api/inspections/${encodeURIComponent(name)}/save`, { options, why }),
  results: (params) => getJson(`/api/results${query(params)}`),
  result: (id) => getJson(`/api/results/${encodeURIComponent(id)}`),
  resultImageUrl: (id, overlay = true) =>
    `/api/results/${encodeURIComponent(id)}/image.png?overlay=${overlay ? 1 : 0}`,
  stats: (params) => getJson(`/api/stats${query(params)}`),
  operatorCalls: () => getJson("/api/operator/calls"),
  answerCall: (id, choice, reason) =>
    postJson(`/api/operator/calls/${encodeURIComponent(id)}/answer`,
      reason ? { choice, reason } : { choice }),
};
