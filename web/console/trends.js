// A drive's trends on its page: the last 30 s live from the stream (every
// status the page received), or zoomed out to 5 min, 15 min or the hour
// from the daemon's history (GET /api/v1/drives/{drive}/history), which
// keeps every drive's status whether a page was open or not: recent
// points as polled, older ones as one-second buckets, drawn as their mean
// with a band from minimum to maximum, so a short spike is not averaged
// away. A zoomed-out view is read again every few seconds.

import { drivePath, get, ApiError } from './api.js';
import { h, Note } from './ui.js';

/** The views: seconds shown, and how often a history view is read again, ms. */
export const WINDOWS = [
  { s: 30, label: '30 s', refreshMs: 0 },
  { s: 300, label: '5 min', refreshMs: 2000 },
  { s: 900, label: '15 min', refreshMs: 5000 },
  { s: 3600, label: '1 h', refreshMs: 10000 },
];

/**
 * The plots: key in the page's live history, label and unit, colour, and
 * the history's field with its own label where it differs (the history
 * keeps the angle within the turn, not whole turns).
 */
const PLOTS = [
  { key: 'speed', label: 'Speed', unit: 'rpm', colour: '#1d4ed8', field: 'speed_rpm' },
  { key: 'position', label: 'Position', unit: 'turns', colour: '#047857', field: 'angle_deg', fieldLabel: 'Angle in the turn', fieldUnit: '°' },
  { key: 'current', label: 'Current', unit: 'A', colour: '#b45309', field: 'current_a' },
  { key: 'temperature', label: 'Temperature', unit: '°C', colour: '#b91c1c', field: 'temperature_c' },
];

/** Points asked of the history: about one per pixel of a wide plot. */
const MAX_POINTS = 1500;

/** The time axis's labels: hours and minutes where the ticks are whole
 * minutes apart, seconds too where they are closer. */
function clock(seconds, step) {
  const d = new Date(seconds * 1000);
  const two = (n) => String(n).padStart(2, '0');
  const hm = `${two(d.getHours())}:${two(d.getMinutes())}`;
  return step >= 60 ? hm : `${hm}:${two(d.getSeconds())}`;
}

/** The widths of a label with seconds ("00:00:00") and without ("00:00")
 * in the axis's font, CSS px. */
let widths = null;
function labelWidths(u) {
  if (!widths) {
    const font = Array.isArray(u.axes[0].font) ? u.axes[0].font[0] : '12px sans-serif';
    const ctx = document.createElement('canvas').getContext('2d');
    ctx.font = font;
    const dpr = window.devicePixelRatio || 1;
    widths = { seconds: ctx.measureText('00:00:00').width / dpr, minutes: ctx.measureText('00:00').width / dpr };
  }
  return widths;
}

/** Room between two labels, px. */
const GAP = 16;

/** The least distance between two ticks, px, for `span` seconds over
 * `plotWidth` px: room for a label with seconds if a step under a minute
 * fits that way, else for one of hours and minutes with a step of a
 * minute or more (the labels then say no seconds). */
function tickSpace(u, _axis, min, max, plotWidth) {
  const w = labelWidths(u);
  const withSeconds = w.seconds + GAP;
  const stepNeeded = ((max - min) * withSeconds) / Math.max(1, plotWidth);
  if (stepNeeded <= 30) return withSeconds;
  // A step of a minute or more: more room than 30 s take, so uPlot does
  // not pick a step under a minute (whose labels would need seconds).
  const halfMinute = (30 * plotWidth) / Math.max(1, max - min);
  return Math.max(w.minutes + GAP, halfMinute + 1);
}

/** The plots' padding: room at the right for half a label, so the label
 * of a tick at the right edge is not cut off. */
export function timePadding() {
  return [null, (u) => Math.ceil(labelWidths(u).seconds / 2) + 2, null, null];
}

/** The plots' x axis: the time of day, with ticks never closer than a
 * label and a gap, so the labels never overlap, whatever the
 * window shown and the plot's width (uPlot picks the step, from seconds to
 * hours, that keeps that space). */
export function timeAxis() {
  return {
    stroke: '#444',
    grid: { stroke: '#e5e7eb' },
    space: tickSpace,
    values: (_, ticks, _axis, _space, step) => ticks.map((t) => clock(t, step)),
  };
}

export class Trends {
  constructor(name, d, store) {
    this.name = name;
    this.d = d;
    this.store = store;
    this.window = WINDOWS[0];
    this.plots = [];
    this.history = null;
    this.range = [0, 0];
    this.timer = null;
    this.asked = 0;
    this.lastDraw = 0;
    this.note = new Note();
    this.title = h('h2', { id: 'plots-h' }, 'Last 30 seconds');
    this.box = h('div', { class: 'plots', dataset: { window: '30', source: 'live' } });
    this.buttons = WINDOWS.map((w) => {
      const b = h('button', { type: 'button', dataset: { zoom: String(w.s) }, 'aria-pressed': String(w === this.window) }, w.label);
      b.addEventListener('click', () => this.zoom(w));
      return b;
    });
    this.section = h('section', { class: 'panel', 'aria-labelledby': 'plots-h' },
      h('div', { class: 'plots-head' }, this.title,
        h('div', { class: 'row zoom', role: 'group', 'aria-label': 'Time shown' }, this.buttons)),
      this.note.el, this.box);
    this.resize = new ResizeObserver(() => {
      for (const p of this.plots) p.u.setSize({ width: Math.max(240, p.box.clientWidth), height: 160 });
    });
    this.build();
  }

  /** (Re)builds the plots for the current view. */
  build() {
    for (const p of this.plots) { this.resize.unobserve(p.box); p.u.destroy(); }
    this.plots = [];
    this.box.replaceChildren();
    if (!window.uPlot) {
      this.box.append(h('p', { role: 'alert' }, 'The plotting library did not load.'));
      return;
    }
    const live = this.window.refreshMs === 0;
    for (const spec of PLOTS) {
      const label = live ? spec.label : spec.fieldLabel || spec.label;
      const unit = live ? spec.unit : spec.fieldUnit || spec.unit;
      const box = h('figure', { class: 'plot', dataset: { plot: spec.key } }, h('figcaption', {}, `${label} (${unit})`));
      this.box.append(box);
      const width = Math.max(240, box.clientWidth || 400);
      const line = { label, stroke: spec.colour, width: 2, points: { show: false } };
      const edge = { stroke: `${spec.colour}66`, width: 1, points: { show: false } };
      const u = new window.uPlot({
        width, height: 160,
        padding: timePadding(),
        legend: { show: false },
        cursor: { drag: { x: false, y: false } },
        // The live view ends at the newest status and spans 10 s at least
        // (whole-second ticks while the page has seen less); a history
        // view shows the range it read.
        scales: { x: { time: true, range: live ? (_, min, max) => (max == null ? [min, max] : [Math.min(min, max - 10), max]) : () => this.range } },
        axes: [
          timeAxis(),
          { stroke: '#444', grid: { stroke: '#e5e7eb' }, size: 56 },
        ],
        series: live ? [{}, line] : [{}, line, { ...edge, label: 'minimum' }, { ...edge, label: 'maximum' }],
        bands: live ? undefined : [{ series: [3, 2], fill: `${spec.colour}22` }],
      }, live ? [[], []] : [[], [], [], []], box);
      // For the tests: the plot a figure holds.
      box.plot = u;
      this.plots.push({ spec, u, box });
      this.resize.observe(box);
    }
  }

  /** Shows the last `w.s` seconds. */
  zoom(w) {
    if (w === this.window) return;
    this.window = w;
    for (const b of this.buttons) b.setAttribute('aria-pressed', String(b.dataset.zoom === String(w.s)));
    this.title.textContent = w.refreshMs === 0 ? 'Last 30 seconds' : `Last ${w.label}, from drivegate's history`;
    this.box.dataset.window = String(w.s);
    this.box.dataset.source = w.refreshMs === 0 ? 'live' : 'history';
    delete this.box.dataset.points;
    clearTimeout(this.timer);
    this.timer = null;
    this.history = null;
    this.note.clear();
    this.build();
    if (w.refreshMs === 0) this.draw(performance.now(), true);
    else this.read();
  }

  /** Reads the history of the current view, then again after its period. */
  async read() {
    const w = this.window;
    const ticket = ++this.asked;
    const until = Date.now();
    const since = until - w.s * 1000;
    const fields = PLOTS.map((p) => p.field).join(',');
    try {
      const r = await get(drivePath(this.name, `/history?fields=${fields}&since=${since}&until=${until}&max_points=${MAX_POINTS}`));
      if (ticket !== this.asked) return;
      this.history = r;
      const t = r.t_ms.map((ms) => ms / 1000);
      // While drivegate has kept less than the window (a daemon started a
      // few minutes ago), the axis starts at the oldest point it kept (10 s
      // at least, for whole-second ticks), so the data fills the plot; the
      // note says how much there is.
      const kept = t.length ? t[t.length - 1] - t[0] : 0;
      const start = t.length && kept < w.s - 5 ? Math.min(t[0], until / 1000 - 10) : since / 1000;
      this.range = [start, until / 1000];
      for (const p of this.plots) {
        const c = r.fields[p.spec.field];
        p.u.setData(c ? [t, c.mean, c.min, c.max] : [t, [], [], []]);
      }
      this.box.dataset.points = String(t.length);
      this.box.dataset.from = String(since);
      this.box.dataset.until = String(until);
      this.store.stats.historyReads = (this.store.stats.historyReads || 0) + 1;
      this.note.set('', t.length === 0 ? 'drivegate has kept nothing of this drive yet'
        : kept < w.s - 5 ? `drivegate has kept ${Math.round(kept)} s of this drive so far (it keeps ${r.minutes} min): the plot starts there` : '');
    } catch (e) {
      if (ticket !== this.asked) return;
      if (e instanceof ApiError && e.status === 404 && !(e.problem && e.problem.drive)) {
        this.note.fail(new Error('this drivegate keeps no history: only the last 30 s this page has seen can be shown'));
        for (const b of this.buttons.slice(1)) b.disabled = true;
        this.zoom(WINDOWS[0]);
        return;
      }
      this.note.fail(e);
    }
    if (ticket === this.asked && this.window === w) this.timer = setTimeout(() => this.read(), w.refreshMs);
  }

  /** Draws the live view (at most 30 times a second); a history view draws when read. */
  draw(now, force = false) {
    if (this.window.refreshMs !== 0 || !this.plots.length) return;
    if (!force && now - this.lastDraw <= 33) return;
    this.lastDraw = now;
    const hist = this.d.history;
    for (const p of this.plots) p.u.setData([hist.t, hist[p.spec.key]]);
    this.box.dataset.points = String(hist.t.length);
    this.store.stats.plotsDrawn = (this.store.stats.plotsDrawn || 0) + this.plots.length;
  }

  dispose() {
    this.asked += 1;
    clearTimeout(this.timer);
    this.resize.disconnect();
    for (const p of this.plots) p.u.destroy();
    this.plots = [];
  }
}
