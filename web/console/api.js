// The REST client: the public API under /api/v1 with the tab's token.
// Every failure becomes an ApiError carrying the API's problem+json, so the
// page can show the daemon's own words next to the control that failed.

const TOKEN_KEY = 'drivegate.token';

/** A refused or failed request: `problem` is the API's problem document. */
export class ApiError extends Error {
  constructor(problem, status) {
    super(problem.detail || problem.title || `HTTP ${status}`);
    this.problem = problem;
    this.status = status;
  }
}

/** The token kept for this tab (sessionStorage: gone when the tab closes). */
export function token() {
  return sessionStorage.getItem(TOKEN_KEY);
}

export function setToken(value) {
  if (value) sessionStorage.setItem(TOKEN_KEY, value);
  else sessionStorage.removeItem(TOKEN_KEY);
}

/** Sends one request; resolves with the JSON body, rejects with ApiError. */
export async function api(method, path, body) {
  const headers = { Accept: 'application/json' };
  const t = token();
  if (t) headers.Authorization = `Bearer ${t}`;
  const init = { method, headers, cache: 'no-store' };
  if (body !== undefined) {
    headers['Content-Type'] = 'application/json';
    init.body = JSON.stringify(body);
  }
  let res;
  try {
    res = await fetch(path, init);
  } catch (e) {
    throw new ApiError({
      title: 'No answer from drivegate',
      detail: `the request did not reach drivegate (${e.message}): check the network and that the daemon runs. Whether a command was carried out is unknown.`,
    }, 0);
  }
  const text = await res.text();
  let json = null;
  try { json = text ? JSON.parse(text) : null; } catch { json = null; }
  if (!res.ok) {
    const problem = json && typeof json === 'object' && json.detail
      ? json
      : { title: res.statusText, detail: text || `HTTP ${res.status}` };
    throw new ApiError(problem, res.status);
  }
  return json;
}

export const get = (path) => api('GET', path);
export const post = (path, body) => api('POST', path, body);
export const put = (path, body) => api('PUT', path, body);

/** `/api/v1/drives/<name>` with the name escaped. */
export const drivePath = (name, rest = '') => `/api/v1/drives/${encodeURIComponent(name)}${rest}`;
