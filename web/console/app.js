// The console's shell: who the user is (token entry), the page's link to
// drivegate and whether the plant's data is live (the header's badge),
// the navigation between pages, the emergency brake on every page and the
// keyboard shortcuts. A page is one module in pages/ with
//   export const page = { id, title, nav, role, match(path), mount(main, params, ctx) }
// where mount returns a function that unmounts it (a page without a `nav`
// of its own may name the entry it is under: `navAs`). Adding a page is
// adding a file and an entry in PAGES.

import { ApiError, drivePath, get, post, setToken, token } from './api.js';
import { Stream } from './stream.js';
import { Store, plantLiveness } from './store.js';
import { h, Note, run, dateTime } from './ui.js';
import { kindWords, subjectOf, textBeside } from './alarms.js';
import { page as overview } from './pages/overview.js';
import { page as drive } from './pages/drive.js';
import { page as settings } from './pages/settings.js';
import { page as commissioning } from './pages/commissioning.js';
import { page as replace } from './pages/replace.js';
import { page as events } from './pages/events.js';
import { page as alarms } from './pages/alarms.js';
import { page as scope } from './pages/scope.js';
import { page as monitor } from './pages/monitor.js';
import { page as config } from './pages/config.js';
import { page as tokens } from './pages/tokens.js';
import { page as certificates } from './pages/certificates.js';

const PAGES = [overview, alarms, drive, settings, commissioning, replace, events, scope, monitor, config, certificates, tokens];

const stream = new Stream();
const store = new Store(stream);
const ctx = { stream, store, brakeDrive, navigate };
let unmount = null;

// For the tests and the benchmark: what the page has received and drawn.
window.drivegate = { stream, store, pages: PAGES.map((p) => p.id) };

function navigate(path) {
  location.hash = `#${path}`;
}

function route() {
  const path = decodeURI(location.hash.replace(/^#/, '')) || '/';
  let found = null;
  let params = null;
  for (const p of PAGES) {
    params = p.match(path);
    if (params) { found = p; break; }
  }
  if (!found) { found = overview; params = {}; }
  if (unmount) { unmount(); unmount = null; }
  const main = document.getElementById('main');
  main.replaceChildren();
  main.dataset.page = found.id;
  if (found.role && !store.can(found.role)) {
    main.append(h('section', { class: 'panel' }, h('h1', {}, found.title),
      h('p', {}, `This page needs the ${found.role} role; this token "${store.me.who}" has the ${store.me.role} role.`)));
  } else {
    unmount = found.mount(main, params, ctx) || null;
  }
  document.title = `${found.title} — drivegate`;
  const current = found.navAs || found.id;
  for (const a of document.querySelectorAll('#nav a')) {
    a.toggleAttribute('aria-current', a.dataset.page === current);
    if (a.dataset.page === current) a.setAttribute('aria-current', 'page');
  }
}

function buildNav() {
  const nav = document.getElementById('nav');
  nav.replaceChildren(...PAGES.filter((p) => p.nav && (!p.role || store.can(p.role)))
    .map((p) => h('a', { href: `#${p.nav.path}`, dataset: { page: p.id }, accesskey: p.nav.key, title: p.nav.tip || (p.nav.label === p.title ? null : p.title) }, p.nav.label)));
}

/**
 * The header's badge: this page's link to drivegate ("connected",
 * "connecting…", "connection lost"), and, while it is open, whether the
 * drives' data is live, so a green badge never stands beside a dead line:
 * "connected · bus down" (red) or "connected · 2 not live" (amber), the
 * second part on a line of its own on a wide screen. The whole story, the
 * buses named, is its tooltip. Drawn at most four times a second.
 */
function drawLink() {
  const el = document.getElementById('conn');
  const { state, reason } = linkState;
  let cls = state;
  let text;
  let title;
  let plantWords = '';
  if (state === 'open') {
    const p = plantLiveness(store);
    const down = p.busesDown.length ? `; down: bus ${p.busesDown.join(', bus ')}` : '';
    const plant = (p.drives === 0 ? 'no drive configured'
      : p.notLive === 0 ? `the data of all ${p.drives} drives is live`
        : `${p.live} of ${p.drives} drives live`) + down;
    text = 'connected';
    if (p.busesDown.length === 1) { cls = 'open down'; plantWords = 'bus down'; }
    else if (p.busesDown.length > 1) { cls = 'open down'; plantWords = `${p.busesDown.length} buses down`; }
    else if (p.notLive > 0) { cls = 'open not-live'; plantWords = `${p.notLive} not live`; }
    title = `This page is connected to drivegate; ${plant}.`;
  } else if (state === 'connecting') {
    text = 'connecting…';
    title = 'This page is connecting to drivegate: nothing shown is live yet.';
  } else {
    text = `connection lost${reason ? ` (${reason})` : ''}: values are stale, reconnecting`;
    title = 'This page lost its connection to drivegate: every value shown is its last, greyed.';
  }
  linkDrawn = performance.now();
  if (el.className !== `conn ${cls}`) el.className = `conn ${cls}`;
  // The plant's words on a line of their own under the link's on a wide
  // screen (the header keeps one row at 1280 px), after a dot on a tablet.
  const whole = plantWords ? `${text} · ${plantWords}` : text;
  if (el.textContent !== whole) {
    el.replaceChildren(...(plantWords
      ? [h('span', { class: 'conn-line' }, text), h('span', { class: 'conn-sep' }, ' · '), h('span', { class: 'conn-line' }, plantWords)]
      : [text]));
  }
  if (el.title !== title) el.title = title;
  document.body.classList.toggle('stale', state !== 'open');
}

let linkState = { state: 'connecting', reason: '' };
let linkTimer = 0;
let linkDrawn = 0;
/**
 * Redraws the badge at once after a quiet spell (a bus going down), at
 * most four times a second while statuses come by the hundred.
 */
function linkChanged() {
  if (linkTimer) return;
  const wait = linkDrawn + 250 - performance.now();
  if (wait <= 0) { drawLink(); return; }
  linkTimer = setTimeout(() => { linkTimer = 0; drawLink(); }, wait);
}

function showConnection(s) {
  linkState = s;
  drawLink();
}

/** Sends the emergency brake to one drive; resolves with the reply. */
function brakeDrive(name) {
  return post(drivePath(name, '/commands/brake'));
}

/** The brake to every drive at once, each at emergency priority. */
async function brakeAll() {
  const note = brakeNote;
  const names = store.order.slice();
  note.pending(`braking ${names.length} drives…`);
  const results = await Promise.allSettled(names.map((n) => brakeDrive(n)));
  const failed = results
    .map((r, i) => (r.status === 'rejected' ? `${names[i]}: ${r.reason instanceof ApiError ? r.reason.message : r.reason}` : null))
    .filter(Boolean);
  if (failed.length === 0) note.ok(`brake confirmed by all ${names.length} drives`);
  else note.fail(new ApiError({ title: `Brake failed on ${failed.length} of ${names.length} drives`, detail: failed.join('; ') }, 0));
  store.log({ kind: 'brake', severity: failed.length ? 'bad' : 'warn', drive: null,
    who: store.me.who, text: `emergency brake of all drives from this page: ${failed.length ? failed.join('; ') : 'all confirmed'}` });
}

const brakeNote = new Note();

function buildHeader() {
  const who = document.getElementById('who');
  // "Token" and "role" in words: a token named "commissioning" or
  // "settings" must not read as the name of a page.
  // Two short lines beside the pages on a wide screen (so the header keeps
  // one row at 1280 px), one line on a tablet.
  const tokenWord = store.me.tokens_required ? 'token' : 'client';
  const role = h('span', { class: 'who-line' },
    h('span', { class: 'who-label sep' }, ' · '),
    h('span', { class: 'who-label' }, 'role '),
    h('span', { class: `role ${store.me.role}`, title: 'What this token may do' }, store.me.role));
  if (store.me.tokens_required) {
    role.append(' ', h('button', { class: 'link', onclick: () => { setToken(null); location.reload(); } }, 'Forget token'));
  }
  who.replaceChildren(
    h('span', { class: 'who-line' },
      h('span', { class: 'who-label' }, `${tokenWord} `),
      h('q', { class: 'token-name', title: store.me.tokens_required ? 'The name of the API token in use' : 'No tokens are configured: this local client is known by its address' }, store.me.who)),
    role);
  const brake = document.getElementById('brake-all');
  brake.hidden = !store.can('operator');
  brake.addEventListener('click', () => brakeAll());
  document.getElementById('brake-note').replaceWith(brakeNote.el);
  brakeNote.el.id = 'brake-note';
}

/**
 * The banner under the header, on every page, while any alarm is not
 * acknowledged: how many, the newest in words, the way to the list and
 * (operator) its acknowledgement.
 */
function alarmBanner() {
  const el = document.getElementById('alarm-banner');
  const note = new Note();
  const draw = () => {
    const a = store.alarms;
    const newest = a.list.find((x) => !x.acknowledged);
    el.hidden = !a.available || a.unacknowledged === 0 || !newest;
    if (el.hidden) { el.replaceChildren(); return; }
    const ack = store.can('operator')
      ? h('button', { type: 'button', dataset: { ack: String(newest.id) } }, 'Acknowledge')
      : null;
    if (ack) {
      ack.addEventListener('click', () => run(ack, note, 'acknowledging…', () => a.acknowledge(newest.id),
        (r) => `acknowledged by ${r.acknowledged_by}`));
    }
    el.dataset.count = String(a.unacknowledged);
    el.replaceChildren(
      h('strong', {}, a.unacknowledged === 1 ? '1 alarm not acknowledged:' : `${a.unacknowledged} alarms not acknowledged:`),
      ' ', h('span', { class: 'newest' }, `${dateTime(newest.raised_at)} ${subjectOf(newest)}: ${kindWords(newest.kind)}, ${textBeside(newest)}${newest.active ? '' : ' (cleared since)'}`),
      ' ', ack, ' ', h('a', { href: '#/alarms' }, 'All alarms'), ' ', note.el);
  };
  store.alarms.subscribe(draw);
  store.alarms.refresh();
}

function shortcuts(e) {
  // Keys typed into a field are the field's (a capital B in a search box
  // must not brake the plant); the brake button is one Tab away.
  const typing = e.target.closest('input, textarea, select, [contenteditable]');
  if (e.ctrlKey || e.metaKey || e.altKey || typing) return;
  if (e.key === 'B' && e.shiftKey && store.can('operator')) {
    e.preventDefault();
    brakeAll();
    return;
  }
  if (document.querySelector('dialog[open]')) return;
  const keys = { o: '/', a: '/alarms', e: '/events', c: '/commissioning', r: '/replace', s: '/settings', p: '/scope', m: '/monitor', g: '/config' };
  if (keys[e.key] && !e.shiftKey) {
    e.preventDefault();
    navigate(keys[e.key]);
  } else if (e.key === '?') {
    e.preventDefault();
    document.getElementById('help').showModal();
  }
}

async function login(message) {
  const dialog = document.getElementById('login');
  const input = dialog.querySelector('input');
  const out = dialog.querySelector('output');
  out.textContent = message || '';
  dialog.showModal();
  input.focus();
  return new Promise((resolve) => {
    dialog.querySelector('form').addEventListener('submit', (e) => {
      e.preventDefault();
      setToken(input.value.trim());
      dialog.close();
      resolve();
    }, { once: true });
  });
}

async function whoami() {
  for (;;) {
    try {
      const me = await get('/api/v1/whoami');
      if (me.role) return me;
      await login('');
    } catch (e) {
      if (e instanceof ApiError && e.status === 401) {
        await login(token() ? `${e.message}. Enter a valid token.` : '');
      } else {
        document.getElementById('main').replaceChildren(h('section', { class: 'panel' },
          h('h1', {}, 'drivegate does not answer'), h('p', { role: 'alert' }, e.message),
          h('button', { onclick: () => location.reload() }, 'Try again')));
        throw e;
      }
    }
  }
}

async function start() {
  store.me = await whoami();
  document.body.dataset.role = store.me.role;
  buildHeader();
  buildNav();
  alarmBanner();
  stream.on('state', showConnection);
  store.subscribe(linkChanged);
  await store.refreshDrives().catch(() => {});
  stream.connect();
  store.watchBuses();
  window.addEventListener('hashchange', route);
  document.addEventListener('keydown', shortcuts);
  route();
}

start().catch((e) => console.warn('drivegate console did not start:', e.message));
