// What the gateway's own pages share (admin: configuration, certificates,
// tokens): their tabs under one entry of the navigation, the reload's
// answer in words, a text saved as a file, a secret copied to the
// clipboard, and dates in words.

import { h, dateTime } from './ui.js';

/** The gateway's pages, in the order of their tabs. */
const TABS = [
  ['config', '/config', 'Configuration'],
  ['certificates', '/certificates', 'Certificates'],
  ['tokens', '/tokens', 'API tokens'],
];

/** The tabs between the gateway's pages, `current` marked. */
export function tabs(current) {
  return h('nav', { class: 'tabs', 'aria-label': 'Gateway pages' },
    TABS.map(([id, path, label]) => h('a', {
      href: `#${path}`, dataset: { tab: id }, 'aria-current': id === current ? 'page' : null,
    }, label)));
}

/**
 * What a reload applied, in words: what changed, what stopped, what
 * could not be done; nothing else.
 */
export function reloadAnswer(reload) {
  const list = (items, cls) => h('ul', { class: cls }, items.map((t) => h('li', {}, t)));
  const parts = [h('h3', {}, 'What the reload did')];
  const changes = (reload.changes || []).filter((c) => c);
  parts.push(changes.length ? list(changes, 'changes') : h('p', {}, 'Nothing changed.'));
  if ((reload.stopped || []).length) {
    parts.push(h('p', { class: 'stopped-head' }, 'Stopped:'), list(reload.stopped, 'stopped'));
  }
  if ((reload.problems || []).length) {
    parts.push(h('p', { class: 'problems-head' }, 'Not done:'), list(reload.problems, 'problems'));
  }
  return h('div', { class: 'reload-answer', dataset: { result: 'reload' } }, ...parts);
}

/** Hands `text` to the browser as a file named `name`. */
export function saveText(name, text) {
  const url = URL.createObjectURL(new Blob([text], { type: 'application/toml' }));
  const a = h('a', { href: url, download: name, hidden: true });
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
}

/**
 * Copies `text` to the clipboard: the Clipboard API where the page is a
 * secure context (localhost, HTTPS), else the older copy command on a
 * selected field, which plain http on a plant network still allows.
 * Resolves true when copied.
 */
export async function copyText(text, field) {
  if (navigator.clipboard && window.isSecureContext) {
    try { await navigator.clipboard.writeText(text); return true; } catch { /* the fallback below */ }
  }
  if (field) {
    field.focus();
    field.select();
    try { return document.execCommand('copy'); } catch { return false; }
  }
  return false;
}

/** "in 12 days" / "3 days ago" / "today", from a date. */
export function fromNow(at) {
  const days = Math.round((new Date(at).getTime() - Date.now()) / 86_400_000);
  if (Number.isNaN(days)) return '–';
  if (days === 0) return 'today';
  return days > 0 ? `in ${days} day${days === 1 ? '' : 's'}` : `${-days} day${days === -1 ? '' : 's'} ago`;
}

/** A date and time, or "never". */
export const when = (at) => (at ? dateTime(at) : 'never');
