// Small DOM helpers shared by the pages: element building, number formats,
// the inline message beside a control, and the confirmation dialog.

/** Builds an element: h('button', {class: 'x', onclick}, 'text', child...). */
export function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith('on') && typeof v === 'function') el.addEventListener(k.slice(2), v);
    else if (k === 'class') el.className = v;
    else if (k === 'dataset') Object.assign(el.dataset, v);
    else if (v === true) el.setAttribute(k, '');
    else el.setAttribute(k, String(v));
  }
  for (const c of children.flat()) {
    if (c === undefined || c === null || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

/** Fixed decimals, or a dash for a missing value. */
export function fmt(value, digits = 0) {
  if (value === undefined || value === null || Number.isNaN(value)) return '–';
  return Number(value).toFixed(digits);
}

/** How long ago, from milliseconds. */
export function age(ms) {
  if (ms === undefined || ms === null) return '–';
  if (ms < 1000) return `${Math.max(0, Math.round(ms))} ms`;
  if (ms < 60_000) return `${(ms / 1000).toFixed(1)} s`;
  if (ms < 3_600_000) return `${Math.floor(ms / 60_000)} min`;
  return `${Math.floor(ms / 3_600_000)} h`;
}

/** Words for the API's snake_case names (over_temperature -> over-temperature). */
export const words = (name) => String(name ?? '–').replaceAll('_', ' ');

/** How long ago, in words a person reads at a glance ("2 min ago"). */
export function ago(ms) {
  if (ms === undefined || ms === null || Number.isNaN(ms)) return 'never';
  if (ms < 2000) return 'just now';
  if (ms < 60_000) return `${Math.floor(ms / 1000)} s ago`;
  if (ms < 3_600_000) return `${Math.floor(ms / 60_000)} min ago`;
  if (ms < 172_800_000) return `${Math.floor(ms / 3_600_000)} h ago`;
  return `${Math.floor(ms / 86_400_000)} days ago`;
}

/** A time of day with milliseconds, for the event log. */
export function clock(date) {
  const d = date instanceof Date ? date : new Date(date);
  return d.toLocaleTimeString([], { hour12: false }) + '.' + String(d.getMilliseconds()).padStart(3, '0');
}

const pad2 = (n) => String(n).padStart(2, '0');

/**
 * Date and time of day, local, to the second ("2026-11-25 14:02:31"): an
 * event, an alarm or a last-seen time read the next morning still says
 * which day it was. ISO order, so it sorts and reads the same everywhere.
 */
export function dateTime(date) {
  const d = date instanceof Date ? date : new Date(date);
  if (Number.isNaN(d.getTime())) return '–';
  return `${d.getFullYear()}-${pad2(d.getMonth() + 1)}-${pad2(d.getDate())} `
    + `${pad2(d.getHours())}:${pad2(d.getMinutes())}:${pad2(d.getSeconds())}`;
}

/** A `<time>` element showing `dateTime(at)`, machine-readable too. */
export function timeEl(at) {
  const d = new Date(at);
  return h('time', { datetime: Number.isNaN(d.getTime()) ? null : d.toISOString() }, dateTime(d));
}

/**
 * The message area beside a control: `pending`, `ok` and `fail` say what
 * happened to the last action in the daemon's own words. Nothing fails
 * silently: every rejected promise a control makes ends up in one of these.
 */
export class Note {
  constructor() {
    this.el = h('output', { class: 'note', 'aria-live': 'polite' });
  }
  pending(text) { this.set('pending', text); }
  ok(text) { this.set('ok', text); }
  fail(error) {
    const p = error && error.problem;
    const title = p && p.title ? `${p.title}: ` : '';
    const range = p && p.valid_range ? ` (valid ${p.valid_range.min} to ${p.valid_range.max} ${p.valid_range.unit || ''})`.trimEnd() : '';
    const detail = p ? (p.detail || '') : String(error && error.message ? error.message : error);
    this.set('fail', `${title}${detail}${detail.includes('valid') ? '' : range}`);
  }
  clear() { this.set('', ''); }
  set(kind, text) {
    this.el.className = `note ${kind}`;
    this.el.textContent = text;
    this.el.setAttribute('role', kind === 'fail' ? 'alert' : 'status');
  }
}

/**
 * Runs `action` (a function returning a promise) for a button: disables it
 * meanwhile and reports into `note`. Resolves with the result or null.
 */
export async function run(button, note, pendingText, action, okText) {
  if (button) button.disabled = true;
  note.pending(pendingText);
  try {
    const result = await action();
    note.ok(typeof okText === 'function' ? okText(result) : (okText || 'done'));
    return result;
  } catch (e) {
    note.fail(e);
    return null;
  } finally {
    if (button) button.disabled = false;
  }
}

/**
 * Asks for confirmation in a modal dialog: `body` says what will happen.
 * `options.check` adds a checkbox (e.g. "save even while the motor turns")
 * whose state is returned. Resolves {ok, checked}.
 */
export function confirmDialog({ title, body, confirm = 'Confirm', danger = false, check = null }) {
  const dialog = document.getElementById('dialog');
  dialog.replaceChildren();
  const box = check ? h('input', { type: 'checkbox', id: 'dialog-check' }) : null;
  const ok = h('button', { class: danger ? 'danger' : 'primary', value: 'ok' }, confirm);
  const cancel = h('button', { value: 'cancel', autofocus: true }, 'Cancel');
  const form = h('form', { method: 'dialog' },
    h('h2', { id: 'dialog-title' }, title),
    ...[].concat(body).map((p) => (p instanceof Node ? p : h('p', {}, p))),
    check ? h('p', {}, h('label', {}, box, ' ', check)) : null,
    h('div', { class: 'buttons' }, cancel, ok));
  dialog.setAttribute('aria-labelledby', 'dialog-title');
  dialog.append(form);
  return new Promise((resolve) => {
    dialog.addEventListener('close', () => {
      resolve({ ok: dialog.returnValue === 'ok', checked: box ? box.checked : false });
    }, { once: true });
    dialog.returnValue = 'cancel';
    dialog.showModal();
    cancel.focus();
  });
}

/** A labelled number input. */
export function numberField(label, attrs = {}) {
  const id = `f-${Math.random().toString(36).slice(2, 9)}`;
  const input = h('input', { type: 'text', inputmode: 'decimal', id, autocomplete: 'off', ...attrs });
  const wrap = h('label', { class: 'field', for: id }, h('span', {}, label), input);
  return { wrap, input, value: () => parseNumber(input.value) };
}

/** A number typed by a person ("1,5" too), or NaN. */
export function parseNumber(text) {
  const t = String(text).trim().replace(',', '.');
  if (t === '') return NaN;
  return Number(t);
}
