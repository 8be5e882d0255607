// Commissioning (admin): which units answer on a bus (a scan with
// progress), the guarded address assignment (the manual's broadcast to
// unit 0, only after a scan found exactly one drive on the bus),
// calibration and fine-tuning with progress, set zero, soft reset and
// factory reset, each behind a confirmation that says what happens. A
// scan's drives that are not configured can be added to the configuration
// file (its comments kept) and reloaded, without a restart.

import { drivePath, post } from '../api.js';
import { h, Note, run, numberField, confirmDialog, fmt } from '../ui.js';
import { scanBus, broadcastVerdict, followProcedure, scanTable } from '../scan.js';

export const page = {
  id: 'commissioning',
  title: 'Commissioning',
  role: 'admin',
  nav: { path: '/commissioning', label: 'Commissioning', key: 'c' },
  match: (path) => (path === '/commissioning' ? {} : null),
  mount,
};

/** Calibration takes "about 4 s" (manual 1.3). */
const CALIBRATION_S = 4;

function mount(main, _params, ctx) {
  const { store } = ctx;
  const buses = [...new Set(store.order.map((n) => store.drives.get(n).bus))];
  for (const b of store.buses.keys()) if (!buses.includes(b)) buses.push(b);
  const state = { lastScan: null, cancelled: false };
  main.append(
    scanSection(buses, state, store),
    addressSection(buses, state),
    procedureSection(ctx));
  return () => { state.cancelled = true; };
}

function busPicker(buses, id) {
  return h('select', { id, 'aria-label': 'Bus' }, buses.map((b) => h('option', { value: b }, b)));
}

function scanSection(buses, state, store) {
  const bus = busPicker(buses, 'scan-bus');
  const from = numberField('From unit', { value: '1', size: 4, dataset: { field: 'scan-from' } });
  const to = numberField('To unit', { value: '32', size: 4, dataset: { field: 'scan-to' } });
  const start = h('button', { type: 'button', class: 'primary', dataset: { action: 'scan' } }, 'Scan');
  const stop = h('button', { type: 'button', disabled: true }, 'Stop');
  const progress = h('progress', { max: 1, value: 0, 'aria-label': 'Scan progress' });
  const result = h('div', { class: 'scan-result', 'aria-live': 'polite' });
  const adding = h('div', { class: 'scan-add' });
  const note = new Note();
  let stopping = false;
  stop.addEventListener('click', () => { stopping = true; });
  start.addEventListener('click', async () => {
    const a = from.value(); const b = to.value();
    if (!Number.isInteger(a) || !Number.isInteger(b)) { note.fail(new Error('type whole unit numbers, 1 to 255')); return; }
    stopping = false;
    start.disabled = true; stop.disabled = false;
    let found = { bus: bus.value, from: a, to: b, answered: [], garbled: [], missing: [], silent: 0, not_scanned: [], complete: false };
    progress.max = Math.max(1, b - a + 1); progress.value = 0;
    note.pending(`scanning units ${a} to ${b} of bus ${bus.value}; each silent unit costs one response timeout`);
    try {
      found = await scanBus(bus.value, a, b, {
        progress: (f, done) => { progress.value = done; result.replaceChildren(scanTable(f)); found = f; },
        stop: () => stopping || state.cancelled,
      });
      state.lastScan = found;
      note.ok(`${found.complete ? 'scanned' : 'stopped'}: ${found.answered.length} answered, ${found.garbled.length} garbled, ${found.silent} silent${found.not_scanned.length ? `, ${found.not_scanned.length} not read (bus busy: scan again)` : ''}`);
    } catch (e) {
      note.fail(e);
    } finally {
      start.disabled = false; stop.disabled = true;
      result.replaceChildren(scanTable(found));
      adding.replaceChildren(...addToConfiguration(found, store));
      document.dispatchEvent(new CustomEvent('drivegate-scan'));
    }
  });
  return h('section', { class: 'panel', 'aria-labelledby': 'scan-h' },
    h('h1', { id: 'scan-h' }, 'Bus scan'),
    h('p', { class: 'hint' }, 'Reads the status of every unit in the range, between the polls of the configured drives.'),
    h('div', { class: 'row' }, h('label', { class: 'field' }, h('span', {}, 'Bus'), bus), from.wrap, to.wrap, start, stop),
    progress, note.el, result, adding);
}

/**
 * "Add to configuration": the [[bus.drive]] tables of the drives a scan
 * found that are not configured, with suggested names, and a button that
 * writes them into the configuration file and reloads it. The daemon
 * refuses the write if the file changed since it was shown here.
 */
function addToConfiguration(found, store) {
  const news = found.answered.filter((a) => !a.configured_as && a.status);
  if (!news.length) return [];
  const drives = news.map((a) => ({ unit: a.unit, name: `${found.bus}-${a.unit}` }));
  const tables = h('pre', { class: 'toml', dataset: { field: 'new-drives' } },
    drives.map((d) => `[[bus.drive]]\nunit = ${d.unit}\nname = "${d.name}"\n`).join('\n'));
  const note = new Note();
  const write = h('button', { type: 'button', class: 'primary', disabled: true, dataset: { action: 'add-to-config' } },
    'Write into the configuration and reload');
  let sha256 = null;
  post('/api/v1/config/drives', { bus: found.bus, drives, dry_run: true })
    .then((r) => {
      tables.textContent = r.tables;
      sha256 = r.sha256;
      write.disabled = false;
      note.ok(`to be added to bus ${found.bus} in ${r.file}`);
    })
    .catch((e) => note.fail(e));
  write.addEventListener('click', async () => {
    const r = await run(write, note, 'writing the configuration and reloading',
      () => post('/api/v1/config/drives', { bus: found.bus, drives, base_sha256: sha256 }),
      (r) => `written and reloaded: ${r.reload.changes.join('; ')}`);
    if (r) {
      write.disabled = true;
      await store.refreshDrives().catch(() => {});
    }
  });
  return [
    h('h2', {}, 'Add to configuration'),
    h('p', { class: 'hint' }, `Drives that answered but are not configured, as [[bus.drive]] sections of bus ${found.bus}; rename them in the file later if you like.`),
    tables, h('div', { class: 'row' }, write), note.el,
  ];
}


function addressSection(buses, state) {
  const bus = busPicker(buses, 'address-bus');
  const address = numberField('New address (1 to 255)', { size: 4, dataset: { field: 'new-address' } });
  const only = h('input', { type: 'checkbox', id: 'only-drive' });
  const go = h('button', { type: 'button', class: 'danger', dataset: { action: 'set-address' } }, 'Set address…');
  const check = h('p', { class: 'check', role: 'status' });
  const note = new Note();
  const verdict = () => broadcastVerdict(state.lastScan, bus.value);
  const refresh = () => {
    const v = verdict();
    check.textContent = v.text;
    check.className = `check ${v.ok ? 'good' : 'bad'}`;
    go.disabled = !v.ok;
  };
  bus.addEventListener('change', refresh);
  document.addEventListener('drivegate-scan', refresh);
  refresh();
  go.addEventListener('click', async () => {
    const a = address.value();
    if (!only.checked) { note.fail(new Error('tick the box that this drive is the only one on the bus')); return; }
    const answer = await confirmDialog({
      title: `Broadcast address ${Number.isFinite(a) ? a : '?'} on bus ${bus.value}?`,
      body: [
        'The address is sent as a broadcast to unit 0 (manual 1.2): every drive that hears it takes the new address. Only one drive may be connected.',
        'drivegate then reads the status at the new address and reports whether the drive answers there. Afterwards set unit = N in that drive\'s [[bus.drive]] section and restart drivegate.',
      ],
      confirm: 'Broadcast the address', danger: true,
    });
    if (!answer.ok) return;
    run(go, note, 'broadcasting…', () => post(`/api/v1/buses/${encodeURIComponent(bus.value)}/address`, { address: a, only_drive_on_bus: only.checked }),
      (r) => `the drive answers at address ${r.address}${r.configured_as ? ` (configured as ${r.configured_as})` : ''}. ${r.note}`);
  });
  return h('section', { class: 'panel', 'aria-labelledby': 'addr-h' },
    h('h1', { id: 'addr-h' }, 'Address assignment'),
    h('ol', { class: 'steps' },
      h('li', {}, 'Connect only the new drive to the bus.'),
      h('li', {}, 'Scan the bus over units 1 to 255 (above).'),
      h('li', {}, 'When exactly one drive answers, give it its address.')),
    h('div', { class: 'row' }, h('label', { class: 'field' }, h('span', {}, 'Bus'), bus), address.wrap),
    check,
    h('p', {}, h('label', {}, only, ' This drive is the only one connected to this bus')),
    h('div', { class: 'row' }, go), note.el);
}

function procedureSection({ store }) {
  const drive = h('select', { id: 'proc-drive', 'aria-label': 'Drive' }, store.order.map((n) => h('option', { value: n }, n)));
  const progress = h('progress', { max: 1, value: 0, 'aria-label': 'Procedure progress' });
  const progressText = h('span', { role: 'status', class: 'progress-text' });
  const note = new Note();
  const send = (cmd, force = false) => post(drivePath(drive.value, `/commands/${cmd}${force ? '?force=true' : ''}`));

  /** Follows a procedure the drive runs by itself, with its progress shown. */
  const follow = (name, label, expectedS) => followProcedure(store, name, expectedS, ({ t, s }) => {
    progress.max = expectedS || 1;
    progress.value = expectedS ? Math.min(t, expectedS) : 0;
    if (!expectedS) progress.removeAttribute('value');
    progressText.textContent = `${label}: ${fmt(t, 1)} s${expectedS ? ` of about ${expectedS} s` : ''}${s && s.speed_rpm !== 0 ? ', motor turning' : ''}`;
  });

  const procedure = (cmd, label, expectedS, body) => async () => {
    const name = drive.value;
    const a = await confirmDialog({ title: `${label} on ${name}?`, body, confirm: label });
    if (!a.ok) return;
    const r = await run(null, note, `${label}: sending…`, () => send(cmd), `${label} started: the drive confirmed the command`);
    if (!r) return;
    const { t, s } = await follow(name, label, expectedS);
    if (s && (s.fault !== 'none' || s.stalled)) note.fail(new Error(`${label} ended with ${s.stalled ? 'a stall' : `fault ${s.fault.replaceAll('_', ' ')}`} after ${fmt(t, 1)} s`));
    else note.ok(`${label} done after ${fmt(t, 1)} s${s ? `; the drive reports ${s.calibrated ? 'calibrated' : 'NOT calibrated'}` : ''}`);
  };

  const button = (label, action, cls = '') => {
    const b = h('button', { type: 'button', class: cls }, label);
    b.addEventListener('click', action);
    return b;
  };
  const simple = (cmd, label, body, danger, force) => async () => {
    const name = drive.value;
    const a = await confirmDialog({ title: `${label} on ${name}?`, body, confirm: label, danger, check: force || null });
    if (a.ok) run(null, note, `${label}…`, () => send(cmd, a.checked), `${label}: confirmed by the drive`);
  };
  return h('section', { class: 'panel', 'aria-labelledby': 'proc-h' },
    h('h1', { id: 'proc-h' }, 'Calibration and resets'),
    h('div', { class: 'row' }, h('label', { class: 'field' }, h('span', {}, 'Drive'), drive)),
    h('div', { class: 'row' },
      button('Calibrate…', procedure('calibrate', 'Calibration', CALIBRATION_S,
        ['The drive calibrates its encoder angle: the motor nudges for about 4 s (manual 1.3). Commands are refused meanwhile.'])),
      button('Fine-tune…', procedure('fine-tune', 'Fine-tuning', null,
        ['The drive fine-tunes its calibration: the motor turns both ways until the values satisfy it, then stops. Only after a calibration. Keep the load free to move.'])),
      button('Set zero…', simple('set-zero', 'Set zero', ['The current position becomes zero. It is lost at power-off (manual 1.3).'])),
      button('Soft reset…', simple('soft-reset', 'Soft reset', ['The drive restarts, as after a power cycle: it does not answer for a moment and comes back with the settings saved in flash.'], true)),
      button('Factory reset…', simple('factory-reset', 'Factory reset',
        ['Ramps, stall protection and inertia go back to the factory values, in flash. drivegate refuses while the motor turns.'], true,
        'Reset even while the motor turns (force; logged)'), 'danger')),
    progress, progressText, note.el);
}
