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

// The WebSocket subprotocols a stream offers: "drivegate", and the token
// as "drivegate.bearer.<base64url of the token>" (a header, so it stays out
// of the URL, where proxies and logs would keep it). The daemon answers
// "drivegate" only.
export function streamProtocols() {
  const t = token();
  if (!t) return ['drivegate'];
  let bytes = '';
  for (const b of new TextEncoder().encode(t)) bytes += String.fromCharCode(b);
  const b64 = btoa(bytes).replace(/\+/g, '-').replace(/\//g, '_').replace(/=+$/, '');
  return ['drivegate', `drivegate.bearer.${b64}`];
}

export function setToken(value) {
  if (value) sessionStorage.setItem(TOKEN_KEY, value);
  else sessionStorage.removeItem(TOKEN_KEY);
}

/** Sends one request; resolves with the JSON body, rejects with ApiError. */
export async function api(method, path, body) {
  return (await request(method, path, { body })).json;
}

/**
 * Sends one request with extra headers (`If-Match`); resolves with
 * {json, etag}, rejects with ApiError.
 */
export async function request(method, path, { body, headers: extra = {} } = {}) {
  const headers = { Accept: 'application/json', ...extra };
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
  if (!res.ok) throw refusal(res, json, text);
  const etag = (res.headers.get('ETag') || '').replace(/^W\//, '').replaceAll('"', '');
  return { json, etag };
}

/** The ApiError of a refused answer: its problem+json, or its words. */
function refusal(res, json, text) {
  const problem = json && typeof json === 'object' && json.detail
    ? json
    : { title: res.statusText, detail: text || `HTTP ${res.status}` };
  return new ApiError(problem, res.status);
}

/**
 * Downloads one of the API's files (a capture's CSV, the monitor's PCAP)
 * with the tab's token, and hands it to the browser as a file under the
 * name the API gives it. A plain link cannot carry the token, so the file
 * is fetched here and saved from memory. Resolves {name, bytes}.
 */
export async function download(path, fallbackName = null) {
  const headers = {};
  const t = token();
  if (t) headers.Authorization = `Bearer ${t}`;
  let res;
  try {
    res = await fetch(path, { headers, cache: 'no-store' });
  } catch (e) {
    throw new ApiError({ title: 'No answer from drivegate', detail: `the download did not reach drivegate (${e.message})` }, 0);
  }
  if (!res.ok) {
    const text = await res.text();
    let json = null;
    try { json = JSON.parse(text); } catch { json = null; }
    throw refusal(res, json, text);
  }
  const blob = await res.blob();
  const named = /filename="([^"]+)"/.exec(res.headers.get('Content-Disposition') || '');
  const name = named ? named[1] : (fallbackName || path.split('?')[0].split('/').pop());
  const url = URL.createObjectURL(blob);
  const a = document.createElement('a');
  a.href = url;
  a.download = name;
  a.hidden = true;
  document.body.append(a);
  a.click();
  a.remove();
  // The browser has taken the file once the click returned; the URL is
  // kept a while for slow save dialogs, then freed.
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
  return { name, bytes: blob.size };
}

/** `/api/v1/buses/<name>` with the name escaped. */
export const busPath = (name, rest = '') => `/api/v1/buses/${encodeURIComponent(name)}${rest}`;

export const get = (path) => api('GET', path);
export const post = (path, body) => api('POST', path, body);
export const put = (path, body) => api('PUT', path, body);
export const del = (path) => api('DELETE', path);

/** `/api/v1/drives/<name>` with the name escaped. */
export const drivePath = (name, rest = '') => `/api/v1/drives/${encodeURIComponent(name)}${rest}`;
