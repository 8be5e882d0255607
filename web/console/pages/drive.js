// One drive: its live values and plots, its controls by role (activation,
// mode, hold-to-jog, go to a position, torque, fault reset, brake), what it
// holds (read from it), and its events.

import { drivePath, get, post, put } from '../api.js';
import { History, positionTurns } from '../store.js';
import { Jog, DEFAULT_LEASE_MS } from '../jog.js';
import { h, fmt, age, words, Note, run, numberField, clock } from '../ui.js';
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

const PLOTS = [
  ['speed', 'Speed', 'rpm', '#1d4ed8'],
  ['position', 'Position', 'turns', '#047857'],
  ['current', 'Current', 'A', '#b45309'],
  ['temperature', 'Temperature', '°C', '#b91c1c'],
];

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

  // Header and live values.
  const badge = h('span', { class: 'badge' });
  const values = h('dl', { class: 'values' });
  const valueCells = {};
  for (const [key, label] of [['state', 'State'], ['mode', 'Mode'], ['speed', 'Speed'], ['position', 'Position'],
    ['current', 'Current'], ['voltage', 'Voltage'], ['temperature', 'Temperature'], ['flags', 'Flags'], ['age', 'Last status']]) {
    valueCells[key] = h('dd', { dataset: { value: key } });
    values.append(h('div', {}, h('dt', {}, label), valueCells[key]));
  }
  const head = h('section', { class: 'panel drive-head' },
    h('h1', {}, name, ' ', badge),
    h('p', { class: 'where' }, `bus ${d.bus}, unit ${d.unit}, gear ratio ${d.gearRatio}`,
      store.can('admin') ? [' · ', h('a', { href: `#/settings/${encodeURIComponent(name)}` }, 'Settings')] : null),
    values);
  main.append(head);

  // Controls.
  let jog = null;
  let controls = null;
  if (store.can('operator')) {
    controls = buildControls(name, d, ctx);
    jog = controls.jog;
    main.append(controls.section);
    cleanups.push(() => controls.jog.dispose(), () => controls.torqueJog.dispose());
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

  // Plots.
  const plotBox = h('div', { class: 'plots' });
  main.append(h('section', { class: 'panel', 'aria-labelledby': 'plots-h' },
    h('h2', { id: 'plots-h' }, 'Last 30 seconds'), plotBox));
  const plots = [];
  if (window.uPlot) {
    for (const [key, label, unit, colour] of PLOTS) {
      const box = h('figure', { class: 'plot', dataset: { plot: key } }, h('figcaption', {}, `${label} (${unit})`));
      plotBox.append(box);
      const width = Math.max(240, box.clientWidth || 400);
      const u = new window.uPlot({
        width, height: 160,
        legend: { show: false },
        cursor: { drag: { x: false, y: false } },
        scales: { x: { time: true } },
        axes: [
          { stroke: '#444', grid: { stroke: '#e5e7eb' }, values: (_, ticks) => ticks.map(timeOfDay) },
          { stroke: '#444', grid: { stroke: '#e5e7eb' }, size: 56 },
        ],
        series: [{}, { label, stroke: colour, width: 2, points: { show: false } }],
      }, [[], []], box);
      plots.push({ key, u, box });
    }
    const resize = new ResizeObserver(() => {
      for (const p of plots) p.u.setSize({ width: Math.max(240, p.box.clientWidth), height: 160 });
    });
    for (const p of plots) resize.observe(p.box);
    cleanups.push(() => resize.disconnect(), () => plots.forEach((p) => p.u.destroy()));
  } else {
    plotBox.append(h('p', { role: 'alert' }, 'The plotting library did not load.'));
  }

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
  main.append(h('section', { class: 'panel', 'aria-labelledby': 'held-h' },
    h('h2', { id: 'held-h' }, 'Settings held by the drive'), held, h('div', { class: 'row' }, refresh, heldNote.el)));
  readHeld();

  // Events of this drive.
  const eventList = h('ol', { class: 'events compact', reversed: true });
  main.append(h('section', { class: 'panel', 'aria-labelledby': 'ev-h' },
    h('h2', { id: 'ev-h' }, 'Events of this drive ', h('a', { href: '#/events', class: 'small' }, 'all events')), eventList));
  const eventItem = (e) => h('li', { class: e.severity }, h('time', {}, clock(e.at)), ' ', h('span', { class: 'kind' }, e.kind), ' ',
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
  let lastPlot = 0;
  function draw() {
    frame = 0;
    const now = performance.now();
    const s = d.status;
    const c = condition(d, stream.state !== 'open');
    badge.textContent = c.text;
    badge.className = `badge ${c.cls}`;
    head.className = `panel drive-head ${c.cls}`;
    const set = (k, t) => { if (valueCells[k].textContent !== t) valueCells[k].textContent = t; };
    set('state', s ? `${s.active ? 'active' : 'inactive'}${s.fault !== 'none' ? `, fault ${words(s.fault)}` : ''}${s.stalled ? ', stalled' : ''}` : d.link);
    set('mode', s ? words(s.mode) : '–');
    set('speed', s ? `${fmt(s.speed_rpm)} rpm` : '–');
    set('position', s ? `${fmt(positionTurns(s), 3)} turns (${fmt(s.turns)} t, ${fmt(s.angle_deg, 2)}°)` : '–');
    set('current', s ? `${fmt(s.current_a, 2)} A` : '–');
    set('voltage', s ? `${fmt(s.voltage_v)} V` : '–');
    set('temperature', s ? `${fmt(s.temperature_c)} °C` : '–');
    set('flags', s ? `${s.calibrated ? 'calibrated' : 'not calibrated'}, STATUS 0x${s.flags.toString(16).padStart(4, '0')}` : '–');
    set('age', d.receivedAt !== undefined ? `${age(now - d.receivedAt)} ago` : '–');
    if (controls) controls.show(s);
    // Plots at most 30 times a second.
    if (plots.length && now - lastPlot > 33) {
      lastPlot = now;
      const hist = d.history;
      for (const p of plots) p.u.setData([hist.t, hist[p.key]]);
      store.stats.plotsDrawn = (store.stats.plotsDrawn || 0) + plots.length;
    }
  }
  const schedule = () => { if (!frame) frame = requestAnimationFrame(draw); };
  cleanups.push(store.subscribe((n) => { if (n === name || n === null) schedule(); }));
  const ages = setInterval(schedule, 250);
  cleanups.push(() => clearInterval(ages), () => frame && cancelAnimationFrame(frame));
  draw();
  return () => cleanups.forEach((f) => f());
}

/** 24-hour time of day for the plots' axis. */
function timeOfDay(seconds) {
  return new Date(seconds * 1000).toLocaleTimeString([], { hour12: false });
}

function settingsTable(r) {
  const rows = [
    ['Speed setpoint', `${r.setpoints.speed_rpm} rpm`],
    ['Position setpoint', `${fmt(r.setpoints.position_deg, 2)}°`],
    ['Torque setpoint', `${fmt(r.setpoints.torque_a, 3)} A (${r.setpoints.torque_counts} counts)`],
    ['Over-current limit', `${fmt(r.protection.limit_a, 2)} A (${r.protection.limit_counts} counts) for ${r.protection.stall_ms} ms`],
    ['Speed ramp', r.speed_ramp.alpha === 0 ? 'off (alpha 0)'
      : `alpha ${r.speed_ramp.alpha}: 0 to 1000 rpm in ${fmt(speedRampTime(r.speed_ramp.alpha, 1000, r.gear_ratio), 3)} s`],
    ['Position ramp', r.position_ramp.alpha === 0 ? 'off (alpha 0)'
      : `alpha ${r.position_ramp.alpha}: 180° in ${fmt(positionRampTime(r.position_ramp.alpha, 180), 3)} s`],
    ['Load inertia', `${r.inertia_ratio} × rotor`],
    ['Controlled by', r.rs485_control ? 'RS-485 (this gateway)' : 'CAN (RS-485 setpoints are ignored)'],
  ];
  return h('table', { class: 'kv' }, h('tbody', {}, rows.map(([k, v]) => h('tr', {}, h('th', { scope: 'row' }, k), h('td', {}, v)))));
}

function buildControls(name, d, { store, stream, brakeDrive }) {
  const section = h('section', { class: 'panel controls', 'aria-labelledby': 'ctl-h' }, h('h2', { id: 'ctl-h' }, 'Control'));

  // Brake.
  const brakeNote = new Note();
  const brake = h('button', { type: 'button', class: 'estop', 'aria-keyshortcuts': 'b' }, `BRAKE ${name.toUpperCase()} `, h('kbd', {}, 'b'));
  brake.addEventListener('click', () => run(null, brakeNote, 'braking…', () => brakeDrive(name),
    () => 'brake confirmed by the drive; its lease (if any) has ended'));
  section.append(h('div', { class: 'group brake-group' }, brake, brakeNote.el));

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

  /** Marks the drive's current mode and activation on the buttons. */
  const show = (st) => {
    for (const b of modeButtons) b.setAttribute('aria-pressed', String(!!st && st.mode === b.dataset.mode));
    for (const b of activation.children) {
      const on = st && ((b.dataset.command === 'activate' && st.active) || (b.dataset.command === 'deactivate' && !st.active));
      b.setAttribute('aria-pressed', String(!!on));
    }
  };
  return { section, jog, torqueJog, brake, show };
}
