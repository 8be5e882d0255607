// One drive: its live values and plots, its controls by role (activation,
// mode, hold-to-jog, go to a position, torque, fault reset, brake), what it
// holds (read from it), and its events.

import { download, drivePath, get, post, put } from '../api.js';
import { History, positionText, driftWords, freshnessOf } from '../store.js';
import { Jog, DEFAULT_LEASE_MS } from '../jog.js';
import { SpeedSetpoint } from '../setpoint.js';
import { activeAlarmsOf } from '../alarms.js';
import { Trends } from '../trends.js';
import { h, fmt, age, ago, words, Note, run, numberField, parseNumber, clock, dateTime, timeEl } from '../ui.js';
import { condition } from './overview.js';
import { speedRampTime, positionRampTime } from '../ramps.js';

export const page = {
  id: 'drive',
  title: 'Drive',
  nav: null,
  match: (path) => {
    const m = /^\/drive\/([^/]+)$/.exec(path);
    return m ? { name: decodeURIComponent(m[1]) } : null;
  },
  mount,
};

function mount(main, { name }, ctx) {
  const { store, stream } = ctx;
  const d = store.drives.get(name);
  if (!d) {
    main.append(h('section', { class: 'panel' }, h('h1', {}, name),
      h('p', { role: 'alert' }, `No drive named "${name}" is configured. `, h('a', { href: '#/' }, 'Back to the overview'))));
    return null;
  }
  if (!d.history) d.history = new History(30);
  const cleanups = [];

  // Header and live values: plain ones in view, the raw registers
  // (STATUS flags, counts) in a details view closed by default.
  const badge = h('span', { class: 'badge' });
  // Whether it holds its declared settings ([bus.drive.settings]).
  const drift = h('span', { class: 'badge drift', hidden: true, dataset: { drift: '' } });
  const values = h('dl', { class: 'values' });
  const valueCells = {};
  for (const [key, label] of [['state', 'State'], ['mode', 'Mode'], ['speed', 'Speed'], ['position', 'Position'],
    ['current', 'Current'], ['voltage', 'Voltage'], ['temperature', 'Temperature'], ['calibration', 'Encoder'], ['age', 'Last status']]) {
    valueCells[key] = h('dd', { dataset: { value: key } });
    values.append(h('div', {}, h('dt', {}, label), valueCells[key]));
  }
  const rawValues = h('dl', { class: 'values raw' });
  for (const [key, label] of [['flags', 'STATUS register'], ['fault_code', 'Fault code'], ['turns', 'Turns counter'],
    ['angle', 'Angle in the turn'], ['current_counts', 'Current (counts, 1 A = 128)'], ['seen_at', 'Status read at']]) {
    valueCells[key] = h('dd', { dataset: { value: key } });
    rawValues.append(h('div', {}, h('dt', {}, label), valueCells[key]));
  }
  const details = h('details', { class: 'raw', dataset: { details: 'status' } },
    h('summary', {}, 'Details: raw status registers'), rawValues);
  // Offline: the values below are the last ones the drive sent, not live.
  const lastSeen = h('p', { class: 'last-seen', role: 'status', hidden: true });
  // What drivegate says of why (the port's error, the last failed poll).
  const lastSeenWhy = h('p', { class: 'last-seen-why', hidden: true });
  // A fault: what it means and what to check, from drivegate's alarms.
  const faultHelp = h('div', { class: 'fault-help', role: 'alert', hidden: true });
  const head = h('section', { class: 'panel drive-head' },
    h('h1', {}, name, ' ', badge, ' ', drift),
    h('p', { class: 'where' }, `bus ${d.bus}, unit ${d.unit}, gear ratio ${d.gearRatio}`,
      store.can('admin') ? [' · ', h('a', { href: `#/settings/${encodeURIComponent(name)}` }, 'Settings')] : null),
    lastSeen, lastSeenWhy, faultHelp, values, details);
  main.append(head);
  const help = faultHelpView(name, faultHelp, store);
  cleanups.push(() => help.dispose());

  // Controls.
  let jog = null;
  let controls = null;
  if (store.can('operator')) {
    controls = buildControls(name, d, ctx);
    jog = controls.jog;
    main.append(controls.section);
    cleanups.push(() => controls.jog.dispose(), () => controls.torqueJog.dispose(), () => controls.speed.dispose());
    const keys = (e) => {
      if (e.ctrlKey || e.metaKey || e.altKey) return;
      if (e.target.closest('input, textarea, select, [contenteditable]') || document.querySelector('dialog[open]')) return;
      if (e.key === 'ArrowRight' || e.key === 'ArrowLeft') {
        e.preventDefault();
        if (!e.repeat) jog.press(e.key === 'ArrowRight' ? 1 : -1);
      } else if (e.key === 'b' && !e.shiftKey) {
        e.preventDefault();
        controls.brake.click();
      }
    };
    const keysUp = (e) => {
      if (e.key === 'ArrowRight' || e.key === 'ArrowLeft') jog.release();
    };
    document.addEventListener('keydown', keys);
    document.addEventListener('keyup', keysUp);
    cleanups.push(() => {
      document.removeEventListener('keydown', keys);
      document.removeEventListener('keyup', keysUp);
    });
  }

  // Trends: the last 30 s live, or up to the hour from the history.
  const trends = new Trends(name, d, store);
  main.append(trends.section);
  cleanups.push(() => trends.dispose());

  // What the drive holds.
  const held = h('div', { class: 'held' });
  const heldNote = new Note();
  const refresh = h('button', { type: 'button', dataset: { read: 'settings' } }, 'Read from the drive');
  let heldAt = Infinity;
  const readHeld = () => run(refresh, heldNote, 'reading…', () => get(drivePath(name, '/settings')), (r) => {
    held.replaceChildren(settingsTable(r));
    heldAt = Date.parse(r.read_at);
    held.dataset.stale = 'false';
    return `read at ${clock(r.read_at)}`;
  });
  refresh.addEventListener('click', readHeld);
  // The same document as a file, which PUT .../settings (and the
  // replace-a-drive page) takes back as it is.
  const saveFile = h('button', { type: 'button', dataset: { read: 'file' } }, 'Save to a file');
  saveFile.addEventListener('click', () => run(saveFile, heldNote, 'reading the drive…',
    () => download(drivePath(name, '/settings?download=1'), `${name}-settings.json`),
    (r) => `saved as ${r.name}: the settings read from the drive now, for the replace-a-drive page or PUT .../settings`));
  main.append(h('section', { class: 'panel', 'aria-labelledby': 'held-h' },
    h('h2', { id: 'held-h' }, 'Settings held by the drive'), held, h('div', { class: 'row' }, refresh, saveFile, heldNote.el)));
  readHeld();

  // Events of this drive.
  const eventList = h('ol', { class: 'events compact', reversed: true });
  main.append(h('section', { class: 'panel', 'aria-labelledby': 'ev-h' },
    h('h2', { id: 'ev-h' }, 'Events of this drive ', h('a', { href: '#/events', class: 'small' }, 'all events')), eventList));
  const eventItem = (e) => h('li', { class: e.severity }, timeEl(e.at), ' ', h('span', { class: 'kind' }, e.kind), ' ',
    e.who ? h('span', { class: 'who' }, e.who) : null, ' ', e.text);
  const mine = store.events.filter((e) => e.drive === name).slice(-50).reverse();
  eventList.replaceChildren(...mine.map(eventItem));
  cleanups.push(store.onEvent((e) => {
    if (e.drive !== name) return;
    // A write since the read-back: the table no longer says what the
    // drive holds.
    if (e.kind === 'write' && e.at > heldAt && held.dataset.stale !== 'true') {
      held.dataset.stale = 'true';
      heldNote.set('warn', `read at ${clock(heldAt)}; written since (${clock(e.at)}): read again to see what the drive holds now`);
    }
    eventList.prepend(eventItem(e));
    while (eventList.children.length > 50) eventList.lastChild.remove();
  }));

  // Drawing, at most once per frame.
  let frame = 0;
  function draw() {
    frame = 0;
    const now = performance.now();
    const s = d.status;
    const c = condition(d, stream.state !== 'open');
    badge.textContent = c.text;
    badge.className = `badge ${c.cls}`;
    head.className = `panel drive-head ${c.cls}`;
    const set = (k, t) => { if (valueCells[k].textContent !== t) valueCells[k].textContent = t; };
    // Values that are not live (drivegate's freshness) are the last the
    // drive sent: greyed, with why and since when above them.
    const f = freshnessOf(d, now, store.buses.get(d.bus));
    const seen = d.receivedAt !== undefined ? ago(now - d.receivedAt) : 'never';
    values.classList.toggle('not-live', !f.live);
    head.dataset.link = d.link || 'unknown';
    head.dataset.freshness = f.freshness;
    lastSeen.hidden = f.live;
    if (f.live) lastSeenWhy.hidden = true;
    else {
      const text = f.text;
      const whole = f.command ? `${text} ${f.command} ${f.after}` : text;
      if (lastSeen.textContent !== whole) {
        lastSeen.replaceChildren(text, ...(f.command ? [' ', h('code', {}, f.command), ` ${f.after}`] : []));
      }
      const why = f.why && !text.includes(f.why) ? f.why : '';
      if (lastSeenWhy.textContent !== why) lastSeenWhy.textContent = why;
      lastSeenWhy.hidden = !why;
    }
    set('state', s ? `${s.active ? 'active' : 'inactive'}${s.fault !== 'none' ? `, fault ${words(s.fault)}` : ''}${s.stalled ? ', stalled' : ''}` : f.short || '–');
    set('mode', s ? words(s.mode) : '–');
    set('speed', s ? `${fmt(s.speed_rpm)} rpm` : '–');
    set('position', positionText(s));
    set('current', s ? `${fmt(s.current_a, 2)} A` : '–');
    set('voltage', s ? `${fmt(s.voltage_v)} V` : '–');
    set('temperature', s ? `${fmt(s.temperature_c)} °C` : '–');
    set('calibration', s ? (s.calibrated ? 'calibrated' : 'not calibrated') : '–');
    set('age', d.receivedAt === undefined ? '–' : !f.live ? `last seen ${seen}` : `${age(now - d.receivedAt)} ago`);
    set('flags', s ? `0x${s.flags.toString(16).padStart(4, '0')}` : '–');
    set('fault_code', s ? `${s.fault_code} (${words(s.fault)})` : '–');
    set('turns', s ? String(s.turns) : '–');
    set('angle', s ? `${fmt(s.angle_deg, 2)}°` : '–');
    set('current_counts', s && s.current_counts !== undefined ? String(s.current_counts) : '–');
    set('seen_at', d.seenAt ? dateTime(d.seenAt) : '–');
    help.show(s);
    const dec = d.declared;
    drift.hidden = !dec || !dec.checked_at;
    if (dec && dec.checked_at) {
      const text = dec.drift ? 'settings differ from the declaration' : 'declared settings held';
      if (drift.textContent !== text) {
        drift.textContent = text;
        drift.className = `badge drift ${dec.drift ? 'stalled' : 'ok'}`;
        drift.dataset.drift = String(!!dec.drift);
        drift.title = dec.drift ? `${driftWords(dec.differences)} (checked ${dateTime(dec.checked_at)})` : `checked ${dateTime(dec.checked_at)}`;
      }
    }
    if (controls) controls.show(s);
    trends.draw(now);
  }
  const schedule = () => { if (!frame) frame = requestAnimationFrame(draw); };
  cleanups.push(store.subscribe((n) => { if (n === name || n === null) schedule(); }));
  const ages = setInterval(schedule, 250);
  cleanups.push(() => clearInterval(ages), () => frame && cancelAnimationFrame(frame));
  draw();
  return () => cleanups.forEach((f) => f());
}

/**
 * What a fault or a stall means and what to check: the help text of the
 * drive's active alarm, from drivegate's alarms (written from the maker's
 * manual), never a copy kept in the page.
 */
function faultHelpView(name, el, store) {
  let shownFor = 'none';
  let asked = 0;
  const render = (s, alarm, unavailable) => {
    const what = s.stalled && s.fault === 'none' ? 'Stalled' : `Fault: ${words(s.fault)}`;
    const parts = [h('strong', {}, what), '. '];
    if (alarm && alarm.help) {
      parts.push(h('span', { class: 'help-label' }, 'What to do: '), h('span', { dataset: { help: alarm.kind || '' } }, alarm.help));
    } else if (unavailable) {
      parts.push(`No help text for it from this drivegate (${unavailable}). Remove the cause, then press Fault reset.`);
    } else {
      parts.push('Looking up what to do…');
    }
    el.replaceChildren(...parts);
  };
  const lookUp = (s) => {
    const ticket = ++asked;
    render(s, null, null);
    activeAlarmsOf(name).then((alarms) => {
      if (ticket !== asked) return;
      if (alarms === null) { render(s, null, 'its alarms API is not available'); return; }
      const kind = s.fault !== 'none' ? 'fault' : 'stall';
      const alarm = alarms.find((a) => a.kind === kind) || alarms.find((a) => a.help);
      render(s, alarm, alarm ? null : 'no active alarm names it yet');
    }).catch((e) => { if (ticket === asked) render(s, null, e.message); });
  };
  const offAlarm = store.onAlarm ? store.onAlarm((a) => {
    if (a.drive === name && shownFor !== 'none') {
      const d = store.drives.get(name);
      if (d && d.status) lookUp(d.status);
    }
  }) : () => {};
  return {
    show(s) {
      const key = s && (s.fault !== 'none' || s.stalled) ? `${s.fault}/${s.stalled}` : 'none';
      if (key === shownFor) return;
      shownFor = key;
      el.hidden = key === 'none';
      if (key !== 'none') lookUp(s);
    },
    dispose: () => offAlarm(),
  };
}

function settingsTable(r) {
  const rows = [
    ['Speed setpoint', `${r.setpoints.speed_rpm} rpm`],
    ['Position setpoint', `${fmt(r.setpoints.position_deg, 2)}°`],
    ['Torque setpoint', `${fmt(r.setpoints.torque_a, 3)} A`],
    ['Over-current limit', `${fmt(r.protection.limit_a, 2)} A for ${r.protection.stall_ms} ms`],
    ['Speed ramp', r.speed_ramp.alpha === 0 ? 'off: speed changes at once'
      : `0 to 1000 rpm in ${fmt(speedRampTime(r.speed_ramp.alpha, 1000, r.gear_ratio), 3)} s`],
    ['Position ramp', r.position_ramp.alpha === 0 ? 'off: moves at once'
      : `180° in ${fmt(positionRampTime(r.position_ramp.alpha, 180), 3)} s`],
    ['Load inertia', `${r.inertia_ratio} × rotor`],
    ['Controlled by', r.rs485_control ? 'RS-485 (this gateway)' : 'CAN (RS-485 setpoints are ignored)'],
  ];
  // The registers' own numbers, for whoever compares with the manual.
  const raw = [
    ['Torque setpoint', `${r.setpoints.torque_counts} counts`],
    ['Over-current limit', `${r.protection.limit_counts} counts`],
    ['Speed ramp', `alpha ${r.speed_ramp.alpha}`],
    ['Position ramp', `alpha ${r.position_ramp.alpha}`],
  ];
  const table = (list) => h('table', { class: 'kv' }, h('tbody', {}, list.map(([k, v]) => h('tr', {}, h('th', { scope: 'row' }, k), h('td', {}, v)))));
  return h('div', {}, table(rows),
    h('details', { class: 'raw', dataset: { details: 'settings' } }, h('summary', {}, 'Details: raw register values'), table(raw)));
}

function buildControls(name, d, { store, stream, brakeDrive }) {
  const section = h('section', { class: 'panel controls', 'aria-labelledby': 'ctl-h' }, h('h2', { id: 'ctl-h' }, 'Control'));

  // Brake.
  const brakeNote = new Note();
  const brake = h('button', { type: 'button', class: 'estop', 'aria-keyshortcuts': 'b' }, `BRAKE ${name.toUpperCase()} `, h('kbd', {}, 'b'));
  brake.addEventListener('click', () => run(null, brakeNote, 'braking…', () => brakeDrive(name),
    () => 'brake confirmed by the drive; its lease (if any) has ended'));
  section.append(h('div', { class: 'group brake-group' }, brake,
    h('p', { class: 'not-estop', dataset: { note: 'not-estop' } },
      'This brake is a command sent over the network: it is not a safety-rated emergency stop. ',
      'The machine\'s hard-wired emergency stop is what protects people.'),
    brakeNote.el));

  // Activation, fault reset.
  const stateNote = new Note();
  const command = (cmd, text) => {
    const b = h('button', { type: 'button', dataset: { command: cmd } }, text);
    b.addEventListener('click', () => run(b, stateNote, `${text}…`, () => post(drivePath(name, `/commands/${cmd}`)),
      (r) => `${text}: confirmed by the drive (${r.written.map((w) => `${w.register}=${w.raw}`).join(', ')})`));
    return b;
  };
  const activation = h('div', { class: 'row' }, command('activate', 'Activate'), command('deactivate', 'Deactivate'), command('fault-reset', 'Fault reset'));

  // Mode.
  const modeNote = new Note();
  const modeButtons = ['speed', 'position', 'torque'].map((m) => {
    const b = h('button', { type: 'button', dataset: { mode: m } }, `${m[0].toUpperCase()}${m.slice(1)}`);
    b.addEventListener('click', () => run(b, modeNote, `switching to ${m} mode…`,
      () => put(drivePath(name, '/mode'), { mode: m }), `${m} mode: confirmed by the drive`));
    return b;
  });
  section.append(h('div', { class: 'group' }, h('h3', {}, 'Drive'), activation, stateNote.el,
    h('h3', {}, 'Mode'), h('div', { class: 'row', role: 'group', 'aria-label': 'Mode' }, modeButtons), modeNote.el));

  // Hold-to-jog (speed), with the daemon's jog lease.
  const leaseMs = store.me.jog_lease_ms ?? DEFAULT_LEASE_MS;
  const jogNote = new Note();
  const rpm = numberField('Jog speed (rpm)', { value: '60', size: 6, dataset: { field: 'jog-rpm' } });
  const jogState = h('span', { class: 'jog-state', role: 'status', dataset: { jog: 'idle' } }, 'released');
  const report = (note, stateEl) => ({ state, direction, error, why }) => {
    stateEl.dataset.jog = state;
    stateEl.textContent = state === 'running' ? `jogging ${direction > 0 ? 'forward' : 'backward'}`
      : state === 'starting' ? 'starting…'
        : state === 'released' ? `released (${why}): drivegate stops the motor when the ${leaseMs} ms lease runs out`
          : 'released';
    if (error) note.fail(error); else if (state === 'running') note.clear();
  };
  const jog = new Jog(stream, name, (dir) => {
    const v = rpm.value();
    if (!Number.isFinite(v)) throw new Error('type a jog speed in rpm');
    if (d.status && d.status.mode !== 'speed') {
      throw new Error(`jogging drives the motor in speed mode; the drive is in ${words(d.status.mode)} mode: switch to speed mode first`);
    }
    return { speed_rpm: Math.round(Math.abs(v)) * dir };
  }, report(jogNote, jogState), leaseMs);
  const back = h('button', { type: 'button', class: 'jog', dataset: { jog: 'backward' }, 'aria-keyshortcuts': 'ArrowLeft' }, '◀ hold to jog back');
  const fwd = h('button', { type: 'button', class: 'jog', dataset: { jog: 'forward' }, 'aria-keyshortcuts': 'ArrowRight' }, 'hold to jog forward ▶');
  jog.bind(back, -1);
  jog.bind(fwd, 1);
  section.append(h('div', { class: 'group' }, h('h3', {}, 'Jog (speed mode)'),
    h('p', { class: 'hint' }, `Hold a button (or ← / →). The setpoint carries a ${leaseMs} ms lease renewed while held; on release, lost focus, a closed tab or a cut network drivegate stops the motor when the lease runs out.`),
    h('div', { class: 'row' }, rpm.wrap, back, fwd), jogState, jogNote.el));

  const speed = speedSetpointGroup(name, d, stream, store, leaseMs);
  section.append(speed.group);

  // Go to a position.
  const posNote = new Note();
  const deg = numberField('Position (°, −180 to 180)', { value: '0', size: 7, dataset: { field: 'position' } });
  const go = h('button', { type: 'button', dataset: { action: 'goto' } }, 'Go to position');
  go.addEventListener('click', () => run(go, posNote, 'sending…', () => {
    const v = deg.value();
    if (!Number.isFinite(v)) return Promise.reject(new Error('type a position in degrees'));
    return put(drivePath(name, '/setpoint'), { position_deg: v });
  }, (r) => `position setpoint ${r.written[0].value}° confirmed by the drive${d.status && d.status.mode !== 'position' ? ' — it moves once the drive is in position mode' : ''}`));
  section.append(h('div', { class: 'group' }, h('h3', {}, 'Position (position mode)'),
    h('div', { class: 'row' }, deg.wrap, go), posNote.el));

  // Torque, held like the jog.
  const torqueNote = new Note();
  const amps = numberField('Torque current (A)', { value: '0.5', size: 6, dataset: { field: 'torque' } });
  const torqueState = h('span', { class: 'jog-state', role: 'status' }, 'released');
  const torqueJog = new Jog(stream, name, (dir) => {
    const v = amps.value();
    if (!Number.isFinite(v)) throw new Error('type a current in amps');
    return { torque_a: Math.abs(v) * dir };
  }, report(torqueNote, torqueState), leaseMs);
  const tMinus = h('button', { type: 'button', class: 'jog', dataset: { torque: 'negative' } }, '◀ hold −');
  const tPlus = h('button', { type: 'button', class: 'jog', dataset: { torque: 'positive' } }, 'hold + ▶');
  torqueJog.bind(tMinus, -1);
  torqueJog.bind(tPlus, 1);
  section.append(h('div', { class: 'group' }, h('h3', {}, 'Torque (torque mode)'),
    h('p', { class: 'hint' }, 'Applied while held, with the same lease as the jog: an unloaded motor in torque mode speeds up until something stops it.'),
    h('div', { class: 'row' }, amps.wrap, tMinus, tPlus), torqueState, torqueNote.el));

  /**
   * Marks the drive's current mode and activation on the buttons: a
   * pressed button is a state the drive is in (Activate while it is
   * active, its mode), never the absence of one.
   */
  const show = (st) => {
    for (const b of modeButtons) b.setAttribute('aria-pressed', String(!!st && st.mode === b.dataset.mode));
    for (const b of activation.children) {
      const on = !!st && b.dataset.command === 'activate' && st.active;
      b.setAttribute('aria-pressed', String(on));
    }
  };
  return { section, jog, torqueJog, brake, show, speed };
}

/**
 * A speed typed in and kept (speed mode), with the lease chosen: held
 * while this page is open, or for a number of seconds (see setpoint.js).
 */
function speedSetpointGroup(name, d, stream, store, leaseMs) {
  const note = new Note();
  const rpm = numberField('Speed (rpm)', { value: '100', size: 6, dataset: { field: 'setpoint-rpm' } });
  const radio = (value, checked) => h('input', { type: 'radio', name: `lease-${name}`, value, checked, dataset: { lease: value } });
  const whileOpen = radio('page', true);
  const forTime = radio('timed', false);
  const seconds = h('input', { type: 'text', inputmode: 'decimal', size: 4, value: '30', 'aria-label': 'Lease in seconds', dataset: { field: 'lease-s' } });
  const set = h('button', { type: 'button', class: 'primary', dataset: { action: 'set-speed' } }, 'Set speed');
  const stop = h('button', { type: 'button', dataset: { action: 'stop-speed' } }, 'Stop');
  const state = h('span', { class: 'jog-state', role: 'status', dataset: { setpoint: 'idle' } }, 'no setpoint from this field');
  let countdown = null;
  const showState = (key, text) => { state.dataset.setpoint = key; state.textContent = text; };
  const report = ({ state: st, rpm: v, until, why, error, result }) => {
    clearInterval(countdown);
    countdown = null;
    if (error) note.fail(error);
    const confirmed = result && result.written ? ` (confirmed by the drive: ${result.written.map((w) => `${w.quantity} ${w.value}${w.unit ? ` ${w.unit}` : ''}`).join(', ')})` : '';
    if (st === 'sending') { note.pending(`sending ${v} rpm…`); showState('sending', 'sending…'); }
    else if (st === 'held') {
      note.ok(`${v} rpm${confirmed}`);
      showState('held', `${v} rpm, held while this page is open: closing or hiding it, or a cut network, stops the motor within ${leaseMs} ms`);
    } else if (st === 'timed') {
      note.ok(`${v} rpm${confirmed}`);
      const tick = () => {
        const left = Math.max(0, until - Date.now());
        showState('timed', `${v} rpm until ${dateTime(until)} (${Math.ceil(left / 1000)} s left): drivegate then stops the motor, page open or not`);
        if (left === 0) { clearInterval(countdown); countdown = null; }
      };
      tick();
      countdown = setInterval(tick, 1000);
    } else if (st === 'released') showState('released', `released (${why}): drivegate stops the motor when the ${leaseMs} ms lease runs out`);
    else if (st === 'stopping') { note.pending('stopping…'); showState('stopping', 'stopping…'); }
    else if (st === 'stopped') { note.ok(`stopped: zero speed${confirmed}; lease given back`); showState('stopped', 'stopped'); }
    else showState('idle', 'no setpoint from this field');
  };
  const setpoint = new SpeedSetpoint(stream, name, report, leaseMs);
  const send = () => {
    const v = rpm.value();
    if (!Number.isFinite(v)) { note.fail(new Error('type a speed in rpm')); return; }
    if (d.status && d.status.mode !== 'speed') {
      note.fail(new Error(`a speed setpoint moves the motor in speed mode; the drive is in ${words(d.status.mode)} mode: switch to speed mode first`));
      return;
    }
    const value = Math.round(v);
    if (whileOpen.checked) {
      setpoint.hold(value).catch(() => {});
    } else {
      const t = parseNumber(seconds.value);
      if (!Number.isFinite(t) || t <= 0) { note.fail(new Error('type how many seconds the speed is kept')); return; }
      setpoint.timed(value, t).catch(() => {});
    }
  };
  set.addEventListener('click', send);
  rpm.input.addEventListener('keydown', (e) => { if (e.key === 'Enter') { e.preventDefault(); send(); } });
  stop.addEventListener('click', () => setpoint.stop().catch(() => {}));
  // A lease that ended elsewhere (brake, deactivation, a newer setpoint,
  // its time) ends what this field shows.
  // The daemon's lease is the truth: on any lease news of this drive the
  // page asks whether its own lease is still there (one replaced by this
  // field's newer setpoint is).
  const off = store.onEvent((e) => {
    if (e.drive !== name || e.kind !== 'lease') return;
    const shown = state.dataset.setpoint;
    if (!['held', 'timed', 'released'].includes(shown)) return;
    get(drivePath(name)).then((r) => {
      const mine = r.lease && r.lease.owner === store.me.who && r.lease.websocket === (shown !== 'timed');
      if (mine || state.dataset.setpoint !== shown) return;
      setpoint.ended();
      clearInterval(countdown);
      countdown = null;
      showState('ended', `lease ended: ${e.text}`);
    }).catch(() => {});
  });
  const group = h('div', { class: 'group', dataset: { group: 'setpoint' } }, h('h3', {}, 'Speed setpoint (speed mode)'),
    h('div', { class: 'row' }, rpm.wrap, set, stop),
    h('fieldset', { class: 'row lease-choice' }, h('legend', {}, 'Keep it'),
      h('label', {}, whileOpen, ' while this page is open'),
      h('label', {}, forTime, ' for ', seconds, ' s')),
    state, note.el);
  return {
    group,
    dispose: () => { off(); clearInterval(countdown); setpoint.dispose(); },
  };
}
