// Talking to hdrig's REST service from the page: the session cookie travels by itself; state-changing
// requests add the CSRF header the service checks (the value of the readable `hdrig_csrf` cookie).

export const API = "/api/v1";

/** A 4xx/5xx answer, with the service's problem document (RFC 9457: title, detail, errors...). */
export class ProblemError extends Error {
  constructor(status, problem) {
    super(problem.detail || problem.title || `HTTP ${status}`);
    this.status = status;
    this.problem = problem;
  }
}

/** The value of the readable CSRF cookie ("" before login). */
export function csrfToken() {
  for (const part of document.cookie.split(";")) {
    const [name, ...rest] = part.trim().split("=");
    if (name === "hdrig_csrf") return decodeURIComponent(rest.join("="));
  }
  return "";
}

/** Called on any 401: the session is gone or never was, so the page asks for the key again. */
let onUnauthorized = () => {};
export function whenUnauthorized(handler) {
  onUnauthorized = handler;
}

/** One request; JSON in and out. Throws ProblemError on an error status, after telling a 401. */
export async function request(method, path, body) {
  const headers = { Accept: "application/json" };
  if (method !== "GET" && method !== "HEAD") headers["X-CSRF-Token"] = csrfToken();
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const response = await fetch(API + path, {
    method,
    headers,
    credentials: "same-origin",
    body: body === undefined ? undefined : JSON.stringify(body),
  });
  const payload = await readBody(response);
  if (!response.ok) {
    const problem = asProblem(response, payload);
    if (response.status === 401 && path !== "/session") onUnauthorized(problem);
    throw new ProblemError(response.status, problem);
  }
  return payload;
}

async function readBody(response) {
  const text = await response.text();
  if (!text) return null;
  try {
    return JSON.parse(text);
  } catch {
    return text;
  }
}

/** Any error body as a problem document; FastAPI's own `{"detail": [...]}` becomes `errors`. */
function asProblem(response, payload) {
  if (payload && typeof payload === "object" && !Array.isArray(payload)) {
    const problem = { status: response.status, ...payload };
    if (Array.isArray(problem.detail)) {
      problem.errors = problem.errors || problem.detail;
      problem.detail = "";
    }
    if (!problem.title) problem.title = response.statusText || `HTTP ${response.status}`;
    return problem;
  }
  return { status: response.status, title: response.statusText || `HTTP ${response.status}`, detail: payload || "" };
}

/** One line per entry of a problem's `errors` (strings, or {loc|field, msg|message} objects). */
export function errorLines(problem) {
  const errors = problem.errors;
  if (!errors) return [];
  const list = Array.isArray(errors) ? errors : Object.entries(errors).map(([field, msg]) => ({ field, msg }));
  return list.map((e) => {
    if (typeof e === "string") return e;
    const where = Array.isArray(e.loc) ? e.loc.join(".") : e.field || e.loc || e.name || "";
    const what = e.msg || e.message || e.detail || JSON.stringify(e);
    return where ? `${where}: ${what}` : what;
  });
}
