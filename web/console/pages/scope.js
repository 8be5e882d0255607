// The scope: a triggered capture of status fields of one or more drives of
// a bus, at the highest rate the bus allows. Arm it (operator: a capture
// changes what the bus polls), watch it fill from the stream's `scope`
// messages, plot it on the wire's time axis (t = 0 at the trigger), and
// download it as the API's own CSV or JSON. Every refusal (a second capture
// on the bus, a length beyond the limit) is the API's, shown beside the
// control that caused it.

import { busPath, download, get, post, api } from '../api.js';
import { busesOf } from '../store.js';
import { h, fmt, clock, Note, run, numberField } from '../ui.js';

export const page = {
  id: 'scope',
  title: 'Scope',
  nav: { path: '/scope', label: 'Scope', key: 'p' },
  match: (path) => {
    if (path === '/scope') return {};
    const m = /^\/scope\/([^/]+)$/.exec(path);
    return m ? { bus: decodeURIComponent(m[1]) } : null;
  },
  mount,
};

/** The fields a capture can keep, with their units (the API's names). */
const FIELDS = [
  ['speed_rpm', 'speed', 'rpm'], ['angle_deg', 'angle', '°'], ['turns', 'turns', 'turns'],
  ['current_a', 'current', 'A'], ['voltage_v', 'voltage', 'V'], ['temperature_c', 'temperature', '°C'],
  ['active', 'active', '0/1'], ['stalled', 'stalled', '0/1'], ['mode', 'mode', 'code'], ['fault', 'fault', 'code'],
];
const UNIT = Object.fromEntries(FIELDS.map(([n, , u]) => [n, u]));
const LABEL = Object.fromEntries(FIELDS.map(([n, l]) => [n, l]));

const TRIGGERS = [
  ['rising', 'a field rises through a level'],
  ['falling', 'a field falls through a level'],
  ['fault', 'the drive reports a fault'],
  ['stall', 'the drive stalls'],
  ['write', 'a write to the drive (any client)'],
  ['manual', 'by hand ("Trigger now")'],
  ['immediate', 'at once'],
];

const STATES = {
  armed: 'armed: waiting for the trigger',
  triggered: 'triggered: filling',
  complete: 'complete',
  incomplete: 'incomplete: a drive stopped answering, or the bus failed, before the length was reached',
  'timed-out': 'timed out: no trigger within the wait (the pre-trigger samples are kept)',
  cancelled: 'cancelled (what it held is kept)',
};

const COLOURS = ['#1d4ed8', '#b91c1c', '#047857', '#b45309', '#7c3aed', '#0e7490', '#be185d', '#4d7c0f'];
/** How often the plot is redrawn from the API while a capture fills. */
const REFRESH_MS = 1000;
/** Above this many samples the plot waits for the end instead. */
const LIVE_PLOT_MAX = 20000;

function mount(main, params, ctx) {
  const { store, stream, navigate } = ctx;
  const buses = busesOf(store);
  const bus = params.bus || buses[0];
  if (!bus || !buses.includes(bus)) {
    main.append(h('section', { class: 'panel' }, h('h1', {}, 'Scope'),
      h('p', { role: 'alert' }, bus ? `No bus named "${bus}" is configured.` : 'No bus is configured.')));
    return null;
  }
  const drives = store.order.map((n) => store.drives.get(n)).filter((d) => d && d.bus === bus);
  const cleanups = [];
  const operator = store.can('operator');
  // What this page knows of the length it armed (a length in seconds has
  // no sample target in the API's state).
  let armedSeconds = null;

  // Header: the bus and its limits.
  const busSelect = h('select', { 'aria-label': 'Bus', dataset: { filter: 'bus' } },
    buses.map((b) => h('option', { value: b, selected: b === bus }, b)));
  busSelect.addEventListener('change', () => navigate(`/scope/${encodeURIComponent(busSelect.value)}`));
  const limits = h('p', { class: 'hint' });
  main.append(h('section', { class: 'panel' },
    h('h1', {}, 'Scope ', h('span', { class: 'small' }, 'bus '), buses.length > 1 ? h('span', { class: 'filters' }, busSelect) : bus),
    h('p', { class: 'hint' }, 'Captures status fields of chosen drives at the highest rate the bus allows, around a trigger. ',
      'While it runs its drives get the polls; the other drives keep a floor rate and commands keep their priority.'),
    limits));

  // The form (operator).
  const armNote = new Note();
  let form = null;
  if (operator) {
    form = buildForm(drives);
    const arm = h('button', { type: 'button', class: 'primary', dataset: { action: 'arm' } }, 'Arm');
    arm.addEventListener('click', () => {
      let body;
      try {
        body = form.body();
      } catch (e) {
        armNote.fail(e);
        return;
      }
      armedSeconds = body.length.seconds ?? null;
      run(arm, armNote, 'arming…', () => post(busPath(bus, '/scope'), body),
        (s) => { show(s); return `capture ${s.id} armed: ${s.capacity_samples} samples at most (${fmt(s.memory_bytes / 1e6, 2)} MB)`; });
    });
    main.append(h('section', { class: 'panel scope-form', 'aria-labelledby': 'arm-h' },
      h('h2', { id: 'arm-h' }, 'New capture'), form.el,
      h('div', { class: 'row' }, arm, armNote.el)));
  }

  // The capture: state, progress, trigger, controls.
  const stateText = h('p', { class: 'capture-state', role: 'status', dataset: { state: 'none' } }, 'No capture since drivegate started.');
  const progress = h('progress', { max: 1, hidden: true, 'aria-label': 'Capture progress' });
  const counts = h('p', { class: 'progress-text' });
  const fired = h('p', { class: 'trigger-text' });
  const captureNote = new Note();
  const triggerNow = h('button', { type: 'button', dataset: { action: 'trigger' }, hidden: true }, 'Trigger now');
  const cancel = h('button', { type: 'button', class: 'danger', dataset: { action: 'cancel' }, hidden: true }, 'Cancel');
  triggerNow.addEventListener('click', () => run(triggerNow, captureNote, 'triggering…',
    () => post(busPath(bus, '/scope/trigger')), (s) => { show(s); return 'triggered'; }));
  cancel.addEventListener('click', () => run(cancel, captureNote, 'cancelling…',
    () => api('DELETE', busPath(bus, '/scope')), (s) => { show(s); return 'cancelled: what it held is kept'; }));
  main.append(h('section', { class: 'panel', 'aria-labelledby': 'cap-h' },
    h('h2', { id: 'cap-h' }, 'Capture'), stateText, progress, counts, fired,
    operator ? h('div', { class: 'row' }, triggerNow, cancel, captureNote.el) : null));

  // The plots and the downloads.
  const plotBox = h('div', { class: 'scope-plots' });
  const exportNote = new Note();
  const csv = h('button', { type: 'button', dataset: { read: 'csv', download: 'csv' }, disabled: true }, 'Download CSV');
  const json = h('button', { type: 'button', dataset: { read: 'json', download: 'json' }, disabled: true }, 'Download JSON');
  csv.addEventListener('click', () => run(csv, exportNote, 'downloading…', () => download(busPath(bus, '/scope/result.csv')),
    (r) => `${r.name}: ${fmt(r.bytes / 1024, 1)} KB`));
  json.addEventListener('click', () => run(json, exportNote, 'downloading…', () => saveJson(bus, current ? current.id : 0),
    (r) => `${r.name}: ${fmt(r.bytes / 1024, 1)} KB`));
  main.append(h('section', { class: 'panel', 'aria-labelledby': 'plot-h' },
    h('h2', { id: 'plot-h' }, 'Samples ', h('span', { class: 'small' }, 'time on the wire, s from the trigger (each sample at the end of its status request)')),
    plotBox, h('div', { class: 'row' }, csv, json, exportNote.el)));

  const plots = new Plots(plotBox, store);
  cleanups.push(() => plots.destroy());

  let current = null;
  let fetching = false;
  let lastFetch = 0;
  let plottedKey = '';

  /** Shows a capture's state (from the API's answer or a stream message). */
  function show(s) {
    if (!s || s.bus !== bus) return;
    const prev = current;
    current = s;
    stateText.dataset.state = s.state;
    stateText.className = `capture-state ${s.running ? 'running' : s.state === 'complete' ? 'done' : 'ended'}`;
    stateText.textContent = `Capture ${s.id} (${s.drives.join(', ')}; ${s.fields.map((f) => LABEL[f] || f).join(', ')}): ${STATES[s.state] || s.state}`;
    const total = s.pre_trigger_samples + s.post_trigger_samples;
    counts.textContent = `${s.pre_trigger_samples} samples before the trigger, ${s.post_trigger_samples} after${s.target_samples ? ` of ${s.target_samples}` : ''}; `
      + `${fmt(s.rate_hz, 1)} samples/s; ${fmt(s.elapsed_s, 1)} s since armed at ${clock(s.armed_at)}; room for ${s.capacity_samples}`;
    const t = s.trigger;
    fired.textContent = t.fired
      ? `Trigger (${triggerWords(t)}) at ${clock(t.time)}: ${t.what || ''}${t.source ? `, caused by ${t.source}` : ''}`
      : `Trigger: ${triggerWords(t)} (not yet)`;
    fired.dataset.fired = String(t.fired);
    // Progress: of the sample target; of the length in seconds at the
    // rate so far; else only moving.
    progress.hidden = !s.running && s.state !== 'complete';
    if (s.state === 'complete') progress.value = 1;
    else if (s.state === 'armed') progress.removeAttribute('value');
    else if (s.target_samples) progress.value = Math.min(1, s.post_trigger_samples / s.target_samples);
    else if (armedSeconds && s.rate_hz > 0) progress.value = Math.min(0.99, s.post_trigger_samples / (armedSeconds * s.rate_hz));
    else progress.removeAttribute('value');
    triggerNow.hidden = !(s.running && s.state === 'armed');
    cancel.hidden = !s.running;
    csv.disabled = json.disabled = total === 0;
    // The samples: at the end, at the trigger, and every second while it
    // fills (if not too many to fetch that often).
    const key = `${s.id}/${s.state}`;
    const ended = !s.running;
    const due = s.state === 'triggered' && total <= LIVE_PLOT_MAX && performance.now() - lastFetch > REFRESH_MS;
    if ((ended && key !== plottedKey) || due || (prev && prev.id !== s.id && !s.running)) fetchResult();
    if (s.state === 'armed' && (!prev || prev.id !== s.id)) plots.clear(`capture ${s.id} armed: the plot is drawn once it triggers`);
  }

  // One fetch at a time; a change meanwhile fetches once more after it,
  // so the end of a capture is always drawn.
  let again = false;
  async function fetchResult() {
    if (fetching) { again = true; return; }
    fetching = true;
    try {
      for (let tries = 0; tries < 3; tries += 1) {
        again = false;
        lastFetch = performance.now();
        const r = await get(busPath(bus, '/scope/result'));
        if (current && r.id === current.id) {
          plots.draw(r);
          if (!r.running) plottedKey = `${r.id}/${r.state}`;
        }
        if (!again && !(current && !current.running && plottedKey !== `${current.id}/${current.state}`)) break;
      }
    } catch (e) {
      exportNote.fail(e);
    } finally {
      fetching = false;
    }
  }

  cleanups.push(stream.on('scope', (m) => show(m)));
  get(busPath(bus, '/scope')).then((v) => {
    limits.textContent = `At most ${v.max_samples} samples a capture (${fmt(v.max_memory_bytes / 1e6, 1)} MB), `
      + `${fmt(v.wire_rate_hz, 1)} samples/s on this wire (all captured drives together), `
      + `other drives keep ${fmt(v.floor_rate_hz, 1)} polls/s; the longest wait for a trigger is ${fmt(v.max_wait_s, 0)} s.`;
    if (v.capture) show(v.capture);
  }).catch((e) => { limits.textContent = ''; captureNote.fail(e); exportNote.fail(e); });

  return () => cleanups.forEach((f) => f());
}

function triggerWords(t) {
  const d = t.drive ? ` ${t.drive}` : '';
  switch (t.kind) {
    case 'rising': return `a field of${d} rising through its level`;
    case 'falling': return `a field of${d} falling through its level`;
    case 'fault': return `a fault of${d}`;
    case 'stall': return `a stall of${d}`;
    case 'write': return `a write to${d}`;
    case 'manual': return 'by hand';
    case 'immediate': return 'at once';
    default: return t.kind;
  }
}

/** The JSON result, saved as a file (GET .../scope/result). */
function saveJson(bus, id) {
  return download(busPath(bus, '/scope/result'), `${bus}-capture-${id}.json`);
}

/** The arming form; `body()` builds the API's body or throws a plain Error. */
function buildForm(drives) {
  const el = h('div', { class: 'scope-grid' });
  const names = drives.map((d) => d.name);

  const driveBoxes = drives.map((d, i) => h('label', { class: 'check-item' },
    h('input', { type: 'checkbox', value: d.name, checked: i === 0, dataset: { drive: d.name } }), ` ${d.name} (unit ${d.unit})`));
  el.append(h('fieldset', { class: 'group' }, h('legend', {}, 'Drives'), ...driveBoxes));

  const fieldBoxes = FIELDS.map(([n, l, u]) => h('label', { class: 'check-item' },
    h('input', { type: 'checkbox', value: n, checked: n === 'speed_rpm' || n === 'current_a', dataset: { scopeField: n } }), ` ${l} (${u})`));
  el.append(h('fieldset', { class: 'group' }, h('legend', {}, 'Fields'), ...fieldBoxes));

  const kind = h('select', { dataset: { field: 'trigger' }, id: 'scope-trigger' }, TRIGGERS.map(([v, l]) => h('option', { value: v }, l)));
  const tDrive = h('select', { dataset: { field: 'trigger-drive' }, id: 'scope-trigger-drive' }, names.map((n) => h('option', { value: n }, n)));
  const tField = h('select', { dataset: { field: 'trigger-field' }, id: 'scope-trigger-field' },
    FIELDS.map(([n, l, u]) => h('option', { value: n }, `${l} (${u})`)));
  const level = numberField('Level', { value: '100', size: 8, dataset: { field: 'level' } });
  const levelUnit = h('span', { class: 'unit' });
  const lab = (text, input) => h('label', { class: 'field', for: input.id }, h('span', {}, text), input);
  const driveWrap = lab('Drive', tDrive);
  const fieldWrap = lab('Field', tField);
  const levelWrap = h('span', { class: 'level' }, level.wrap, levelUnit);
  const update = () => {
    const k = kind.value;
    driveWrap.hidden = !['rising', 'falling', 'fault', 'stall', 'write'].includes(k);
    fieldWrap.hidden = levelWrap.hidden = !['rising', 'falling'].includes(k);
    levelUnit.textContent = UNIT[tField.value];
  };
  kind.addEventListener('change', update);
  tField.addEventListener('change', update);
  update();
  el.append(h('fieldset', { class: 'group' }, h('legend', {}, 'Trigger'),
    h('div', { class: 'row' }, lab('When', kind), driveWrap, fieldWrap, levelWrap)));

  const amount = (label, value, unit, key) => {
    const f = numberField(label, { value, size: 6, dataset: { field: key } });
    const u = h('select', { 'aria-label': `${label}: unit`, dataset: { field: `${key}-unit` } },
      h('option', { value: 'samples', selected: unit === 'samples' }, 'samples per drive'),
      h('option', { value: 'seconds', selected: unit === 'seconds' }, 'seconds'));
    return { wrap: h('span', { class: 'amount' }, f.wrap, u), value: f.value, unit: () => u.value, label };
  };
  const pre = amount('Before the trigger', '50', 'samples', 'pre');
  const length = amount('Length from the trigger', '2', 'seconds', 'length');
  const wait = numberField('Wait for the trigger (s)', { value: '300', size: 6, dataset: { field: 'wait' } });
  el.append(h('fieldset', { class: 'group' }, h('legend', {}, 'Length'),
    h('div', { class: 'row' }, pre.wrap, length.wrap, wait.wrap)));

  const number = (v, what) => {
    if (!Number.isFinite(v)) throw new Error(`type a number for ${what}`);
    return v;
  };
  const asAmount = (a) => {
    const v = number(a.value(), a.label.toLowerCase());
    return a.unit() === 'samples' ? { samples: Math.round(v) } : { seconds: v };
  };
  const body = () => {
    const chosen = driveBoxes.map((l) => l.querySelector('input')).filter((i) => i.checked).map((i) => i.value);
    const fields = fieldBoxes.map((l) => l.querySelector('input')).filter((i) => i.checked).map((i) => i.value);
    const k = kind.value;
    const trigger = { type: k };
    if (driveWrap.hidden === false) trigger.drive = tDrive.value;
    if (k === 'rising' || k === 'falling') {
      trigger.field = tField.value;
      trigger.level = number(level.value(), 'the level');
    }
    return {
      drives: chosen,
      fields,
      trigger,
      pre_trigger: asAmount(pre),
      length: asAmount(length),
      wait_s: number(wait.value(), 'the wait'),
    };
  };
  return { el, body };
}

/**
 * One uPlot per field, a series per drive, on a shared axis of seconds
 * from the trigger (a line marks t = 0); cursors move together.
 */
class Plots {
  constructor(box, store) {
    this.box = box;
    this.store = store;
    this.list = [];
    this.resize = new ResizeObserver(() => {
      for (const p of this.list) p.u.setSize({ width: this.width(p.fig), height: 180 });
    });
    this.clear('No samples yet.');
  }

  width(fig) {
    return Math.max(280, fig.clientWidth || this.box.clientWidth || 600);
  }

  clear(text) {
    this.destroyPlots();
    this.box.replaceChildren(h('p', { class: 'hint', dataset: { plot: 'empty' } }, text));
  }

  destroyPlots() {
    for (const p of this.list) { this.resize.unobserve(p.fig); p.u.destroy(); }
    this.list = [];
  }

  destroy() {
    this.destroyPlots();
    this.resize.disconnect();
  }

  /** Draws a result (GET .../scope/result). */
  draw(r) {
    const total = r.traces.reduce((n, t) => n + t.samples, 0);
    if (!window.uPlot) {
      this.clear('The plotting library did not load.');
      return;
    }
    if (total === 0) {
      this.clear('The capture holds no samples.');
      return;
    }
    const { x, index } = mergeTimes(r.traces);
    const same = this.list.length === r.columns.length && this.list.every((p, i) => p.field === r.columns[i].name && p.series === r.traces.length);
    if (!same) {
      this.destroyPlots();
      this.box.replaceChildren();
    }
    r.columns.forEach((col, i) => {
      const data = [x, ...r.traces.map((t, ti) => spread(x.length, index[ti], t.values[col.name]))];
      if (same) {
        this.list[i].u.setData(data);
        return;
      }
      const unit = col.unit || UNIT[col.name] || '';
      const fig = h('figure', { class: 'plot', dataset: { scopePlot: col.name } },
        h('figcaption', {}, `${LABEL[col.name] || col.name}${unit ? ` (${unit})` : ''}`));
      this.box.append(fig);
      const u = new window.uPlot({
        width: this.width(fig), height: 180,
        cursor: { sync: { key: 'scope' }, drag: { x: true, y: false } },
        scales: { x: { time: false } },
        legend: { show: r.traces.length > 1 },
        axes: [
          { stroke: '#444', grid: { stroke: '#e5e7eb' }, label: 's from the trigger', labelSize: 18, values: (_, ticks) => ticks.map((t) => `${t}`) },
          { stroke: '#444', grid: { stroke: '#e5e7eb' }, size: 60, label: unit, labelSize: 18 },
        ],
        series: [
          { label: 't (s)', value: (_, v) => (v === null ? '–' : `${v.toFixed(4)} s`) },
          ...r.traces.map((t, ti) => ({
            label: `${t.drive} ${LABEL[col.name] || col.name}${unit ? ` (${unit})` : ''}`,
            stroke: COLOURS[ti % COLOURS.length], width: 1.5, spanGaps: true,
            points: { show: false },
          })),
        ],
        hooks: { draw: [zeroLine] },
      }, data, fig);
      this.resize.observe(fig);
      this.list.push({ u, fig, field: col.name, series: r.traces.length });
    });
    this.store.stats.scopeSamplesPlotted = total;
    this.store.stats.scopeDraws = (this.store.stats.scopeDraws || 0) + 1;
  }
}

/** The trigger's moment: a dashed line at t = 0. */
function zeroLine(u) {
  const x = u.valToPos(0, 'x', true);
  if (!Number.isFinite(x) || x < u.bbox.left || x > u.bbox.left + u.bbox.width) return;
  const c = u.ctx;
  c.save();
  c.strokeStyle = '#b91c1c';
  c.setLineDash([5, 4]);
  c.lineWidth = 1.5;
  c.beginPath();
  c.moveTo(x, u.bbox.top);
  c.lineTo(x, u.bbox.top + u.bbox.height);
  c.stroke();
  c.restore();
}

/**
 * The union of the traces' times (drives are polled in turn, so each has
 * its own), sorted, and for each trace where its samples fall in it.
 */
function mergeTimes(traces) {
  if (traces.length === 1) return { x: traces[0].t_s, index: [traces[0].t_s.map((_, i) => i)] };
  const all = [];
  traces.forEach((t, ti) => t.t_s.forEach((v, i) => all.push([v, ti, i])));
  all.sort((a, b) => a[0] - b[0]);
  const x = [];
  const index = traces.map((t) => new Array(t.t_s.length));
  for (const [v, ti, i] of all) {
    if (x.length === 0 || x[x.length - 1] !== v) x.push(v);
    index[ti][i] = x.length - 1;
  }
  return { x, index };
}

/** A trace's values placed at their times in the union (null elsewhere). */
function spread(n, where, values) {
  const out = new Array(n).fill(null);
  for (let i = 0; i < where.length; i += 1) out[where[i]] = values[i];
  return out;
}
