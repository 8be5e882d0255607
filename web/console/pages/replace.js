// Replace a drive (admin): a guided procedure for a drive that failed and
// was swapped for a new one at factory settings and an unknown address.
// Each step says its result in words before the next is offered:
//
//   1. choose the drive and where its settings come from (the declaration
//      in the configuration, or a file saved from it), and whether to
//      calibrate;
//   2. connect the new drive alone (the address is a broadcast every
//      connected drive obeys);
//   3. scan the bus over 1 to 255: exactly one drive must answer;
//   4. give it the old drive's address (the guarded broadcast);
//   5. restore the settings: the difference first (a dry run, nothing
//      written), then the writes, confirmed by the drive;
//   6. calibrate, if asked;
//   7. verify: read the settings back and compare again (the difference
//      must be empty).
//
// Every call is the public API's, so each write is checked, confirmed and
// audited by the daemon as from any client; the page adds no rule.

import { ApiError, busPath, drivePath, get, post, put } from '../api.js';
import { h, Note, fmt, dateTime } from '../ui.js';
import { scanBus, broadcastVerdict, followProcedure, scanTable } from '../scan.js';

export const page = {
  id: 'replace',
  title: 'Replace a drive',
  role: 'admin',
  nav: { path: '/replace', label: 'Replace', key: 'r' },
  match: (path) => {
    if (path === '/replace') return { name: null };
    const m = /^\/replace\/([^/]+)$/.exec(path);
    return m ? { name: decodeURIComponent(m[1]) } : null;
  },
  mount,
};

/** Calibration takes "about 4 s" (manual 1.3). */
const CALIBRATION_S = 4;

/** The settings of a document the procedure restores (what PUT .../settings takes). */
const SETTING_KEYS = ['protection', 'speed_ramp', 'position_ramp', 'inertia_ratio', 'rs485_control'];

const STEPS = [
  ['choose', 'Choose the drive and its settings'],
  ['connect', 'Connect the new drive alone'],
  ['scan', 'Scan the bus'],
  ['address', 'Give it the old address'],
  ['settings', 'Restore the settings'],
  ['calibrate', 'Calibrate'],
  ['verify', 'Verify'],
  ['done', 'Done'],
];

/** A setting's value in words ("2.5 A", "on"). */
function valueWords(setting, value, unit) {
  if (typeof value === 'boolean') {
    if (setting === 'rs485_control') return value ? 'RS-485 controls the motor' : 'CAN controls the motor';
    return value ? 'on' : 'off';
  }
  const n = Number(value);
  const text = Number.isInteger(n) ? String(n) : String(Number(n.toFixed(3)));
  return unit ? `${text} ${unit}` : text;
}

/** The diff of PUT .../settings as a table: each setting now and after. */
function diffTable(diff, applied) {
  return h('table', { class: 'kv diff', dataset: { diff: applied ? 'applied' : 'dry-run' } },
    h('thead', {}, h('tr', {}, h('th', {}, 'Setting'), h('th', {}, applied ? 'Before' : 'New drive now'),
      h('th', {}, applied ? 'After (read back)' : 'Will be'), h('th', {}, applied ? 'Result' : ''))),
    h('tbody', {}, diff.settings.map((c) => h('tr', { class: c.changed ? 'changed' : '', dataset: { setting: c.setting } },
      h('th', { scope: 'row' }, c.quantity),
      h('td', {}, valueWords(c.setting, c.before, c.unit)),
      h('td', {}, valueWords(c.setting, c.after, c.unit)),
      h('td', {}, applied ? `${c.result.replaceAll('-', ' ')}${c.detail ? `: ${c.detail}` : ''}` : (c.changed ? 'differs' : 'same'))))));
}

/** Only the settings of a document (GET .../settings, a file, a declaration). */
function settingsOf(doc) {
  const out = {};
  for (const k of SETTING_KEYS) if (doc[k] !== undefined && doc[k] !== null) out[k] = doc[k];
  return out;
}

/** "1 min 23 s" */
function duration(ms) {
  const s = Math.round(ms / 1000);
  return s < 60 ? `${s} s` : `${Math.floor(s / 60)} min ${s % 60} s`;
}

function mount(main, { name }, { store }) {
  const state = { left: false, doc: null, source: '', started: null, scan: null, drive: null, bus: null, unit: null };
  const steps = new Map();
  const list = h('ol', { class: 'procedure' });
  for (const [id, title] of STEPS) {
    const result = h('p', { class: 'result', role: 'status' });
    const body = h('div', { class: 'step-body' });
    const li = h('li', { class: 'step', dataset: { step: id, state: 'waiting' } }, h('h2', {}, title), body, result);
    list.append(li);
    steps.set(id, { li, body, result });
  }
  main.append(h('section', { class: 'panel', 'aria-labelledby': 'replace-h' },
    h('h1', { id: 'replace-h' }, 'Replace a drive'),
    h('p', { class: 'hint' }, 'For a drive that failed and was swapped for a new one, at factory settings and whatever address it came with. '
      + 'Each step says what it found before the next is offered; every write goes through drivegate\'s checks and audit log like any other.'),
    list));

  /** Marks step `id`: state and result in words; an active step shows its body. */
  const mark = (id, st, text, cls = st) => {
    const step = steps.get(id);
    // How long each step took, for whoever plans the next replacement.
    if (st === 'active' && step.li.dataset.state !== 'active') step.since = performance.now();
    if (st !== 'active' && step.since !== undefined) step.li.dataset.ms = String(Math.round(performance.now() - step.since));
    step.li.dataset.state = st;
    step.li.className = `step ${cls}`;
    if (text !== undefined) step.result.textContent = text;
    if (st === 'active') step.li.scrollIntoView({ block: 'nearest' });
  };
  const show = (id, ...children) => steps.get(id).body.replaceChildren(...children);
  const note = (id) => { const n = new Note(); steps.get(id).body.append(n.el); return n; };

  // 1. Choose.
  const drive = h('select', { id: 'replace-drive', 'aria-label': 'Drive', dataset: { field: 'replace-drive' } },
    store.order.map((n) => h('option', { value: n, selected: n === name }, n)));
  const fromDeclared = h('input', { type: 'radio', name: 'replace-source', value: 'declared', dataset: { source: 'declared' } });
  const fromFile = h('input', { type: 'radio', name: 'replace-source', value: 'file', dataset: { source: 'file' } });
  const file = h('input', { type: 'file', accept: '.json,application/json', dataset: { field: 'settings-file' } });
  const declaredWhy = h('span', { class: 'hint' });
  const calibrate = h('input', { type: 'checkbox', dataset: { field: 'calibrate' } });
  const save = h('input', { type: 'checkbox', checked: true, dataset: { field: 'save' } });
  const start = h('button', { type: 'button', class: 'primary', dataset: { action: 'start' } }, 'Start');
  const chooseNote = new Note();
  const where = h('p', { class: 'where' });
  const lookDeclared = async () => {
    const n = drive.value;
    const d = store.drives.get(n);
    where.textContent = d ? `bus ${d.bus}, unit ${d.unit}; now ${d.link || 'unknown'}` : '';
    declaredWhy.textContent = ' (looking…)';
    try {
      const r = await get(drivePath(n, '/settings/declared'));
      if (drive.value !== n) return;
      const count = Object.keys(settingsOf(r)).length;
      declaredWhy.textContent = ` (${count} settings in the configuration)`;
      fromDeclared.disabled = false;
      if (!fromFile.checked) fromDeclared.checked = true;
    } catch (e) {
      if (drive.value !== n) return;
      declaredWhy.textContent = e instanceof ApiError && e.status === 404 ? ` (none: ${e.message})` : ` (${e.message})`;
      fromDeclared.disabled = true;
      fromDeclared.checked = false;
      fromFile.checked = true;
    }
  };
  drive.addEventListener('change', lookDeclared);
  file.addEventListener('change', () => { fromFile.checked = true; });
  show('choose',
    h('div', { class: 'row' }, h('label', { class: 'field' }, h('span', {}, 'Drive to replace'), drive)), where,
    h('fieldset', { class: 'sources' }, h('legend', {}, 'Restore its settings from'),
      h('label', {}, fromDeclared, ' its declared settings', declaredWhy), h('br'),
      h('label', {}, fromFile, ' a file saved from it (drive page: "Save to a file") '), file),
    h('p', {}, h('label', {}, save, ' Save them to the drive\'s flash (kept over power loss; only at standstill)')),
    h('p', {}, h('label', {}, calibrate, ` Calibrate the new drive's encoder (the motor nudges for about ${CALIBRATION_S} s)`)),
    h('div', { class: 'row' }, start), chooseNote.el);
  mark('choose', 'active');
  lookDeclared();

  start.addEventListener('click', async () => {
    const n = drive.value;
    const d = store.drives.get(n);
    if (!d) { chooseNote.fail(new Error('choose a configured drive')); return; }
    start.disabled = true;
    try {
      if (fromDeclared.checked) {
        const r = await get(drivePath(n, '/settings/declared'));
        state.doc = settingsOf(r);
        state.source = `the declaration in the configuration (${Object.keys(state.doc).length} settings)`;
      } else {
        const f = file.files && file.files[0];
        if (!f) throw new Error('choose the file saved from the drive, or its declared settings');
        let parsed;
        try { parsed = JSON.parse(await f.text()); } catch (e) { throw new Error(`${f.name} is not a settings file (not JSON: ${e.message})`); }
        if (!parsed || typeof parsed !== 'object' || Object.keys(settingsOf(parsed)).length === 0) {
          throw new Error(`${f.name} holds no settings (protection, ramps, inertia, RS-485 control): save one from the drive page`);
        }
        state.doc = settingsOf(parsed);
        state.source = `the file ${f.name}${parsed.drive ? `, saved from ${parsed.drive}` : ''}${parsed.read_at ? ` at ${dateTime(parsed.read_at)}` : ''}`;
      }
    } catch (e) {
      chooseNote.fail(e);
      start.disabled = false;
      return;
    }
    state.drive = n; state.bus = d.bus; state.unit = d.unit;
    state.started = performance.now();
    state.startedAt = Date.now();
    state.calibrate = calibrate.checked;
    state.save = save.checked;
    for (const el of [drive, fromDeclared, fromFile, file, calibrate, save]) el.disabled = true;
    audit('started', `settings from ${state.source}; ${state.save ? 'saved to flash' : 'not saved to flash'}; ${state.calibrate ? 'calibration asked' : 'no calibration'}`);
    mark('choose', 'done', `Replacing ${n} (bus ${d.bus}, unit ${d.unit}) with settings from ${state.source}; `
      + `${state.save ? 'saved to flash' : 'not saved to flash'}; ${state.calibrate ? 'calibration asked' : 'no calibration'}. Started at ${dateTime(state.startedAt)}.`);
    connectStep();
  });

  // 2. Connect the new drive alone.
  const connectStep = () => {
    const others = store.order.filter((x) => x !== state.drive && store.drives.get(x).bus === state.bus);
    const alone = h('input', { type: 'checkbox', dataset: { field: 'alone' } });
    const go = h('button', { type: 'button', class: 'primary', dataset: { action: 'scan' } }, `Scan bus ${state.bus}`);
    const n = new Note();
    show('connect',
      h('p', {}, `Fit the new drive in place of ${state.drive}. The address is given by a broadcast that every drive connected to bus ${state.bus} obeys, `
        + `so for the next two steps only the new drive may be connected: ${others.length ? `unplug ${others.join(', ')} (or the bus cable to them)` : 'no other drive is configured on this bus, but unplug any that is'}. `
        + 'Its factory address does not matter.'),
      h('p', {}, h('label', {}, alone, ` Only the new drive is connected to bus ${state.bus}`)),
      h('div', { class: 'row' }, go), n.el);
    mark('connect', 'active');
    go.addEventListener('click', () => {
      if (!alone.checked) { n.fail(new Error(`tick the box once the new drive is the only one connected to bus ${state.bus}`)); return; }
      alone.disabled = true; go.disabled = true;
      n.clear();
      mark('connect', 'done', `Only the new drive is connected to bus ${state.bus} (confirmed by you${others.length ? `: ${others.join(', ')} unplugged` : ''}).`);
      scanStep();
    });
  };

  // 3. Scan 1 to 255.
  const scanStep = async () => {
    const progress = h('progress', { max: 255, value: 0, 'aria-label': 'Scan progress' });
    const table = h('div', { class: 'scan-result' });
    const n = new Note();
    show('scan', h('p', { class: 'hint' }, 'Units 1 to 255, so no drive can hide; each silent unit costs one response timeout.'), progress, n.el, table);
    mark('scan', 'active', '');
    n.pending(`scanning bus ${state.bus}…`);
    let found;
    try {
      found = await scanBus(state.bus, 1, 255, {
        progress: (f, done) => { progress.value = done; n.pending(`scanning bus ${state.bus}: units 1 to ${done}, ${f.answered.length} answered so far`); },
        stop: () => state.left,
      });
    } catch (e) {
      n.fail(e);
      mark('scan', 'failed', `The scan failed: ${e.message}`);
      retry('scan', 'Scan again', scanStep);
      return;
    }
    if (state.left) return;
    n.clear();
    table.replaceChildren(scanTable(found));
    state.scan = found;
    const v = broadcastVerdict(found, state.bus);
    if (!v.ok) {
      mark('scan', 'failed', `${v.text}`);
      retry('scan', 'Scan again', scanStep);
      return;
    }
    const a = found.answered[0];
    const what = a.status ? ` (${a.status.active ? 'active' : 'inactive'}, ${a.status.mode.replaceAll('_', ' ')}, ${a.status.voltage_v} V)` : '';
    if (a.unit === state.unit) {
      mark('scan', 'done', `Exactly one drive answers, at unit ${a.unit}${what}: the address of ${state.drive} already.`);
      mark('address', 'skipped', `Not needed: the new drive answers at unit ${state.unit} already.`);
      settingsStep();
    } else {
      mark('scan', 'done', `Exactly one drive answers, at unit ${a.unit}${what}.`);
      addressStep(a.unit);
    }
  };

  /** A button on a failed step that runs it again. */
  const retry = (id, label, again) => {
    const b = h('button', { type: 'button', dataset: { action: `retry-${id}` } }, label);
    b.addEventListener('click', () => { b.remove(); again(); });
    steps.get(id).body.append(h('div', { class: 'row' }, b));
  };

  // 4. The old address, by the guarded broadcast.
  const addressStep = (found) => {
    const go = h('button', { type: 'button', class: 'primary', dataset: { action: 'set-address' } }, `Give it address ${state.unit}`);
    show('address',
      h('p', {}, `Broadcasts address ${state.unit} on bus ${state.bus} (manual 1.2), with your word that only the new drive is connected, `
        + `then reads its status at unit ${state.unit}.`),
      h('div', { class: 'row' }, go));
    const n = note('address');
    mark('address', 'active', `The new drive answers at unit ${found}; ${state.drive} is unit ${state.unit}.`);
    go.addEventListener('click', async () => {
      go.disabled = true;
      n.pending('broadcasting…');
      try {
        const r = await post(busPath(state.bus, '/address'), { address: state.unit, only_drive_on_bus: true });
        n.clear();
        go.remove();
        mark('address', 'done', `The drive took address ${r.address} and answers there${r.configured_as ? `: drivegate polls it as ${r.configured_as}` : ''}.`);
        settingsStep();
      } catch (e) {
        n.fail(e);
        go.disabled = false;
        mark('address', 'failed', `The address was not set: ${e.message}`);
      }
    });
  };

  // 5. The settings: the difference first, then the writes.
  const settingsStep = async () => {
    const n = new Note();
    const diffBox = h('div');
    const write = h('button', { type: 'button', class: 'primary', dataset: { action: 'write-settings' }, hidden: true },
      state.save ? 'Write and save to flash' : 'Write these settings');
    show('settings', h('p', { class: 'hint' }, `From ${state.source}. First the difference, read from the new drive; nothing is written until you say so.`),
      diffBox, h('div', { class: 'row' }, write), n.el);
    mark('settings', 'active', '');
    n.pending('reading the new drive and comparing (dry run)…');
    let dry;
    try {
      dry = await put(drivePath(state.drive, '/settings?dry_run=true'), { ...state.doc, save: false });
    } catch (e) {
      n.fail(e);
      mark('settings', 'failed', `Could not compare the settings: ${e.message}`);
      retry('settings', 'Compare again', settingsStep);
      return;
    }
    if (state.left) return;
    n.clear();
    diffBox.replaceChildren(diffTable(dry, false));
    write.hidden = false;
    mark('settings', 'active', dry.changed === 0
      ? `The new drive holds all ${dry.settings.length} settings already; nothing written yet.${state.save ? ' Writing saves them to its flash.' : ''}`
      : `${dry.changed} of ${dry.settings.length} settings differ from ${state.source.split(' (')[0]}; nothing written yet.`);
    write.addEventListener('click', async () => {
      write.disabled = true;
      n.pending('writing…');
      try {
        const r = await put(drivePath(state.drive, '/settings'), { ...state.doc, save: state.save });
        diffBox.replaceChildren(diffTable(r, true));
        write.remove();
        if (!r.complete) {
          n.fail(new Error('not every write was confirmed: see the table'));
          mark('settings', 'failed', `Not every setting was written: ${r.settings.filter((c) => c.result === 'failed' || c.result === 'not-sent').map((c) => `${c.quantity}: ${c.detail || c.result}`).join('; ')}`);
          retry('settings', 'Compare and write again', settingsStep);
          return;
        }
        n.clear();
        const written = r.settings.filter((c) => c.result === 'written').length;
        mark('settings', 'done', `${written} settings written and confirmed by the drive${r.save ? ', saved to its flash' : ''}; ${r.changed} changed.`);
        calibrateStep();
      } catch (e) {
        n.fail(e);
        write.disabled = false;
      }
    });
  };

  // 6. Calibration, if asked.
  const calibrateStep = () => {
    if (!state.calibrate) {
      mark('calibrate', 'skipped', 'Not asked.');
      verifyStep();
      return;
    }
    const go = h('button', { type: 'button', class: 'primary', dataset: { action: 'calibrate' } }, 'Calibrate');
    const progress = h('progress', { max: CALIBRATION_S, value: 0, 'aria-label': 'Calibration progress' });
    show('calibrate', h('p', {}, `The drive calibrates its encoder angle: the motor nudges for about ${CALIBRATION_S} s (manual 1.3). Keep the load free to move.`),
      h('div', { class: 'row' }, go), progress);
    const n = note('calibrate');
    mark('calibrate', 'active', '');
    go.addEventListener('click', async () => {
      go.disabled = true;
      n.pending('sending…');
      try {
        await post(drivePath(state.drive, '/commands/calibrate'));
      } catch (e) {
        n.fail(e);
        go.disabled = false;
        return;
      }
      const { t, s } = await followProcedure(store, state.drive, CALIBRATION_S, ({ t: tt }) => {
        progress.value = Math.min(tt, CALIBRATION_S);
        n.pending(`calibrating: ${fmt(tt, 1)} s of about ${CALIBRATION_S} s`);
      });
      if (state.left) return;
      go.remove();
      if (s && (s.fault !== 'none' || s.stalled || !s.calibrated)) {
        n.clear();
        mark('calibrate', 'failed', `The calibration ended after ${fmt(t, 1)} s with ${s.stalled ? 'a stall' : s.fault !== 'none' ? `fault ${s.fault.replaceAll('_', ' ')}` : 'the drive NOT calibrated'}.`);
        retry('calibrate', 'Calibrate again', calibrateStep);
        return;
      }
      n.clear();
      mark('calibrate', 'done', `Calibrated in ${fmt(t, 1)} s: the drive reports its encoder calibrated.`);
      verifyStep();
    });
  };

  // 7. Verify: read back, compare again.
  const verifyStep = async () => {
    const n = new Note();
    const box = h('div');
    show('verify', box, n.el);
    mark('verify', 'active', '');
    n.pending('reading the settings back from the drive…');
    try {
      const held = await get(drivePath(state.drive, '/settings'));
      const again = await put(drivePath(state.drive, '/settings?dry_run=true'), { ...state.doc, save: false });
      if (state.left) return;
      n.clear();
      if (again.changed !== 0) {
        box.replaceChildren(diffTable(again, false));
        mark('verify', 'failed', `Read back at ${dateTime(held.read_at)}: ${again.changed} settings still differ (see the table).`);
        retry('verify', 'Restore the settings again', () => { mark('verify', 'waiting', ''); show('verify'); settingsStep(); });
        return;
      }
      mark('verify', 'done', `Read back at ${dateTime(held.read_at)}: the drive holds every setting of ${state.source.split(' (')[0]}; the difference is empty.`);
      doneStep();
    } catch (e) {
      n.fail(e);
      mark('verify', 'failed', `Could not read the settings back: ${e.message}`);
      retry('verify', 'Verify again', verifyStep);
    }
  };

  const doneStep = () => {
    const took = performance.now() - state.started;
    const others = store.order.filter((x) => x !== state.drive && store.drives.get(x).bus === state.bus);
    steps.get('done').li.dataset.elapsedMs = String(Math.round(took));
    show('done', h('p', {}, others.length ? `Reconnect ${others.join(', ')}: drivegate finds them again by itself within 30 s.` : ''),
      h('p', {}, h('a', { href: `#/drive/${encodeURIComponent(state.drive)}` }, `Open ${state.drive}`)));
    mark('done', 'done', `${state.drive} replaced in ${duration(took)}, from ${dateTime(state.startedAt)} to ${dateTime(Date.now())}.`);
    state.finished = true;
    audit('finished', `replaced in ${duration(took)}; the drive holds the settings of ${state.source.split(' (')[0]}`);
  };

  /**
   * The procedure's start and end in drivegate's audit log, around the
   * writes it makes (each audited as it happens). Said in the page's
   * event log when the daemon cannot note it; the procedure goes on.
   */
  const audit = (event, detail) => {
    post(drivePath(state.drive, '/replacement'), { event, detail: detail.slice(0, 500) })
      .catch((e) => store.log({ kind: 'write', severity: 'warn', drive: state.drive,
        text: `the replacement's ${event} could not be noted in the audit log: ${e.message}` }));
  };

  return () => {
    state.left = true;
    if (state.started !== null && !state.finished) audit('abandoned', 'the page was left before the end');
  };
}
