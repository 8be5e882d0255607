// What the page knows: the drives (from GET /api/v1/drives, then every
// status on the stream), the buses (GET /api/v1/buses, every 2 s), who the
// user is, and the event log. Pages read it and ask to be told of changes;
// the stream is read once here, whatever page is open, so the event log
// keeps everything since the page was opened.

import { get } from './api.js';
import { Alarms, alarmOf, kindWords } from './alarms.js';
import { ago, dateTime } from './ui.js';

const MAX_EVENTS = 5000;
const BUS_PERIOD_MS = 2000;

export class Store {
  constructor(stream) {
    this.stream = stream;
    this.me = null;
    this.drives = new Map();
    this.order = [];
    this.buses = new Map();
    /** True once the list of buses has been read (an empty one means none is configured). */
    this.busesKnown = false;
    this.events = [];
    this.listeners = new Set();
    this.eventListeners = new Set();
    this.stats = { statusReceived: 0, firstValueAt: null };
    this.busTimer = null;
    /** drivegate's alarms (GET /api/v1/alarms), kept by the daemon. */
    this.alarms = new Alarms(stream);
    stream.on('*', (m) => this.onMessage(m));
    stream.on('state', (s) => {
      if (s.state === 'open') this.refreshDrives().catch(() => {});
      this.log({ kind: 'link', severity: s.state === 'open' ? 'info' : 'warn', drive: null,
        text: s.state === 'open' ? 'live connection to drivegate open'
          : s.state === 'closed' ? `live connection to drivegate lost${s.reason ? `: ${s.reason}` : ''}; reconnecting` : null });
      this.changed(null);
    });
  }

  /** Role check for showing controls; the daemon checks every request anyway. */
  can(role) {
    const rank = { viewer: 0, operator: 1, admin: 2 };
    return this.me !== null && rank[this.me.role] >= rank[role];
  }

  async refreshDrives() {
    const list = await get('/api/v1/drives');
    const now = performance.now();
    const order = [];
    for (const v of list) {
      order.push(v.name);
      const d = this.drives.get(v.name) || { name: v.name, history: null };
      d.bus = v.bus;
      d.unit = v.unit;
      d.gearRatio = v.gear_ratio;
      d.link = v.link;
      // How fresh its data is, as drivegate decides it: only `live`
      // values are current (see freshnessOf).
      d.freshness = v.freshness || 'live';
      d.freshnessSince = v.freshness_since || null;
      d.freshnessReason = v.freshness_reason || null;
      d.lease = v.lease;
      // Its declared settings and whether it holds them (absent when none
      // is declared).
      d.declared = v.declared_settings || null;
      if (v.status && (!d.status || d.receivedAt === undefined)) {
        d.status = v.status;
        d.receivedAt = now - (v.age_ms ?? 0);
        d.seenAt = v.last_seen;
      }
      this.drives.set(v.name, d);
    }
    this.order = order;
    this.changed(null);
  }

  async refreshBuses() {
    const list = await get('/api/v1/buses');
    const now = performance.now();
    for (const b of list) {
      const prev = this.buses.get(b.name);
      const c = b.counters;
      const tx = c.ok + c.exceptions + c.timeouts + c.crc_errors + c.bad_replies;
      const errors = c.timeouts + c.crc_errors + c.bad_replies;
      const entry = { ...b, at: now, tx, errors, utilisation: null, errorRate: null };
      // Rates only between two readings of an open port: a bus that is
      // down has no utilisation nor error rate to show as live.
      if (prev && prev.state === 'up' && b.state === 'up') {
        const dt = (now - prev.at) / 1000;
        if (dt > 0) entry.utilisation = Math.min(1, Math.max(0, (c.busy_seconds - prev.counters.busy_seconds) / dt));
        const dtx = tx - prev.tx;
        entry.errorRate = dtx > 0 ? (errors - prev.errors) / dtx : 0;
      }
      this.buses.set(b.name, entry);
    }
    this.busesKnown = true;
    this.changed(null);
  }

  /** Polls the buses' counters while the page is open. */
  watchBuses() {
    const tick = () => {
      this.refreshBuses().catch(() => {}).finally(() => {
        this.busTimer = setTimeout(tick, BUS_PERIOD_MS);
      });
    };
    tick();
  }

  onMessage(m) {
    switch (m.type) {
      case 'status': this.onStatus(m); break;
      case 'online':
        this.setLink(m.drive, 'online');
        this.log({ kind: 'link', severity: 'info', drive: m.drive, text: 'online: answers its polls again' });
        break;
      case 'offline':
        this.setLink(m.drive, 'offline');
        this.log({ kind: 'link', severity: 'bad', drive: m.drive, text: `offline: ${m.reason}` });
        break;
      case 'freshness': this.onFreshness(m); break;
      case 'bus-up':
        this.log({ kind: 'bus', severity: 'info', drive: null, bus: m.bus, text: `bus ${m.bus}: port open` });
        this.refreshBuses().catch(() => {});
        break;
      case 'bus-down': {
        this.log({ kind: 'bus', severity: 'bad', drive: null, bus: m.bus, text: `bus ${m.bus}: port down: ${m.reason}` });
        // The bus's card says it at once, before its counters are read
        // again: no rate of the open port stays on it.
        const b = this.buses.get(m.bus);
        if (b) {
          this.buses.set(m.bus, { ...b, state: 'down', reason: m.reason, since: new Date().toISOString(),
            utilisation: null, errorRate: null });
          this.changed(null);
        }
        this.refreshBuses().catch(() => {});
        break;
      }
      case 'lease-expired':
        this.log({ kind: 'lease', severity: m.ok ? 'warn' : 'bad', drive: m.drive, who: m.owner,
          text: `lease of ${m.owner} ended (${m.reason}); ${m.action}: ${m.result}${m.retrying ? ' — retrying until the drive confirms' : ''}` });
        this.clearLease(m.drive);
        break;
      case 'lease-ended':
        this.log({ kind: 'lease', severity: 'info', drive: m.drive, who: m.owner,
          text: `lease of ${m.owner} ended without a stop (${m.reason})` });
        break;
      case 'lease-stop':
        this.log({ kind: 'lease', severity: m.stopped ? 'info' : 'warn', drive: m.drive, who: m.owner,
          text: `stop after the lease of ${m.owner}: ${m.result} (${m.attempts} tries)` });
        break;
      case 'write':
        this.log({ kind: 'write', severity: m.ok ? 'info' : 'bad', drive: m.drive, who: m.who, bus: m.bus,
          at: Date.parse(m.at), text: `${m.what} → ${m.answer}` });
        break;
      case 'alarm-raised':
      case 'alarm-cleared':
      case 'alarm-acknowledged': {
        const a = alarmOf(m);
        const what = m.type === 'alarm-raised' ? 'raised' : m.type === 'alarm-cleared' ? 'cleared' : `acknowledged by ${a.acknowledged_by || 'an operator'}`;
        this.log({ kind: 'alarm', severity: m.type === 'alarm-raised' ? 'bad' : 'info', drive: a.drive || null, bus: a.bus || null,
          who: m.type === 'alarm-acknowledged' ? a.acknowledged_by : null,
          text: `alarm ${what}: ${kindWords(a.kind)}${a.text ? `: ${a.text}` : ''}` });
        break;
      }
      case 'settings-drift': {
        const d = this.drives.get(m.drive);
        if (d) {
          d.declared = { apply_settings: m.apply_settings, save: m.save, state: m.state, drift: m.drift,
            differences: m.differences || [], checked_at: m.checked_at, detail: m.detail };
          this.changed(m.drive);
        }
        this.log({ kind: 'settings', severity: m.drift ? 'warn' : 'info', drive: m.drive,
          text: m.drift ? `settings differ from the declaration: ${driftWords(m.differences)}` : 'holds its declared settings' });
        break;
      }
      case 'settings-applied':
        this.log({ kind: 'settings', severity: m.complete ? 'info' : 'bad', drive: m.drive, who: m.who,
          text: `settings document ${m.dry_run ? 'compared (dry run)' : 'applied'}: ${m.changed} changed${m.save ? ', saved to flash' : ''}${m.complete ? '' : '; not every write was confirmed'}` });
        break;
      case 'lagged':
        this.log({ kind: 'link', severity: 'warn', drive: null, text: `this page fell behind: ${m.missed} updates skipped` });
        // What was skipped may be a change of freshness: read it again.
        this.refreshDrives().catch(() => {});
        break;
      default:
        break;
    }
  }

  onStatus(m) {
    let d = this.drives.get(m.drive);
    if (!d) {
      d = { name: m.drive, bus: m.bus, unit: m.unit, history: null };
      this.drives.set(m.drive, d);
      this.order.push(m.drive);
    }
    const prev = d.status;
    const s = m.status;
    const now = performance.now();
    d.status = s;
    d.receivedAt = now;
    d.seenAt = m.seen_at;
    if (d.link !== 'online') d.link = 'online';
    this.stats.statusReceived += 1;
    if (this.stats.firstValueAt === null) this.stats.firstValueAt = now;
    if (d.history) d.history.push(Date.parse(m.seen_at) / 1000, s);
    if (prev) {
      if (prev.fault !== s.fault) {
        this.log(s.fault === 'none'
          ? { kind: 'fault', severity: 'info', drive: m.drive, text: `fault cleared (was ${prev.fault.replaceAll('_', ' ')})` }
          : { kind: 'fault', severity: 'bad', drive: m.drive, text: `fault: ${s.fault.replaceAll('_', ' ')} (code ${s.fault_code})` });
      }
      if (prev.stalled !== s.stalled) {
        this.log({ kind: 'stall', severity: s.stalled ? 'bad' : 'info', drive: m.drive,
          text: s.stalled ? `stalled at ${s.current_a.toFixed(2)} A: needs a fault reset` : 'stall cleared' });
      }
      if (prev.active !== s.active) {
        this.log({ kind: 'state', severity: 'info', drive: m.drive, text: s.active ? 'activated' : 'deactivated' });
      }
      if (prev.mode !== s.mode) {
        this.log({ kind: 'state', severity: 'info', drive: m.drive, text: `mode: ${s.mode.replaceAll('_', ' ')}` });
      }
    }
    this.changed(m.drive);
  }

  /** A drive's data changed freshness (drivegate's `freshness` message). */
  onFreshness(m) {
    const d = this.drives.get(m.drive);
    if (!d) return;
    const was = d.freshness;
    d.freshness = m.freshness;
    d.freshnessSince = m.freshness_since || null;
    d.freshnessReason = m.freshness_reason || null;
    // The `offline` message says it already, and a bus down is the bus's
    // own entry: the log gets what no other message tells.
    if (m.freshness === 'stale') {
      this.log({ kind: 'link', severity: 'warn', drive: m.drive, text: `stale: ${m.freshness_reason}` });
    } else if (m.freshness === 'never') {
      this.log({ kind: 'link', severity: 'bad', drive: m.drive, text: `never answered: ${m.freshness_reason}` });
    } else if (m.freshness === 'live' && was === 'stale') {
      this.log({ kind: 'link', severity: 'info', drive: m.drive, text: 'live again: its polls are answered on time' });
    }
    this.changed(m.drive);
  }

  setLink(name, link) {
    const d = this.drives.get(name);
    if (d) { d.link = link; this.changed(name); }
  }

  clearLease(name) {
    const d = this.drives.get(name);
    if (d) { d.lease = null; this.changed(name); }
  }

  /** Adds an entry to the event log (newest last in the array). */
  log(entry) {
    if (!entry.text) return;
    const e = { at: Date.now(), who: null, bus: null, ...entry, id: this.events.length ? this.events[this.events.length - 1].id + 1 : 1 };
    this.events.push(e);
    if (this.events.length > MAX_EVENTS) this.events.splice(0, this.events.length - MAX_EVENTS);
    for (const fn of this.eventListeners) fn(e);
  }

  /** `fn(driveName | null)` on every change (null: several or not one drive). */
  subscribe(fn) {
    this.listeners.add(fn);
    return () => this.listeners.delete(fn);
  }

  /** `fn(alarm)` for every alarm raised, cleared or acknowledged. */
  onAlarm(fn) {
    return this.alarms.onNews((_type, a) => fn(a));
  }

  onEvent(fn) {
    this.eventListeners.add(fn);
    return () => this.eventListeners.delete(fn);
  }

  changed(name) {
    for (const fn of this.listeners) fn(name);
  }
}

/** A drive's differences from its declared settings, in words. */
export function driftWords(differences) {
  const v = (x, unit) => (typeof x === 'boolean' ? (x ? 'on' : 'off') : `${Number.isInteger(x) ? x : Number(Number(x).toFixed(3))}${unit ? ` ${unit}` : ''}`);
  return (differences || []).map((d) => `${d.quantity} ${v(d.drive, d.unit)} (declared ${v(d.declared, d.unit)})`).join(', ') || 'see the drive page';
}

/**
 * Whether a drive's values are current, as drivegate decides it (its
 * `freshness`), and if not what to show: a short state for a table cell,
 * and a sentence that says why and since when. `now` is performance.now();
 * `bus`, the drive's bus from GET /api/v1/buses if known, names its port.
 */
export function freshnessOf(d, now, bus = null) {
  const f = d.freshness || (d.link === 'offline' ? 'offline' : 'live');
  if (f === 'live') return { live: true, freshness: f };
  const seen = d.receivedAt !== undefined ? ago(now - d.receivedAt) : 'never';
  const since = d.freshnessSince ? sinceWords(d.freshnessSince) : null;
  const last = d.status
    ? `The values below are the last it sent, ${seen}${d.seenAt ? ` (${dateTime(d.seenAt)})` : ''}; they are not live.`
    : '';
  const why = d.freshnessReason || '';
  switch (f) {
    case 'bus-down':
      return { live: false, freshness: f, cls: 'offline', short: `bus down${since ? ` since ${since}` : ''}`,
        text: `Bus ${d.bus} is down${since ? ` since ${since}` : ''}: drivegate cannot reach this drive. ${last}`.trim(),
        why };
    case 'offline':
      return { live: false, freshness: f, cls: 'offline', short: `offline, last seen ${seen}`,
        text: d.status
          ? `Offline: drivegate gets no answer from this drive${since ? ` (since ${since})` : ''}. ${last}`
          : 'Offline: drivegate has had no answer from this drive since it started.',
        why };
    case 'stale':
      return { live: false, freshness: f, cls: 'unknown', short: `stale, last status ${seen}`,
        text: `Stale${since ? ` since ${since}` : ''}: ${why || 'its polls are missing'}. ${last}`.trim(),
        why };
    default: {
      // drivegate's words begin "no answer since bus X opened": said here
      // with the time it opened.
      const rest = why.replace(/^no answer since bus \S+ opened ?/, '');
      const port = bus && bus.port && bus.port !== 'sim' ? bus.port : '<the bus\'s port>';
      return { live: false, freshness: 'never', cls: 'unknown', short: 'never answered',
        text: rest !== why
          ? `Never answered since bus ${d.bus} opened${since ? ` at ${since}` : ''} ${rest}.`
          : `Never answered${since ? ` (bus ${d.bus} open since ${since})` : ''}: ${why || 'no status yet'}.`,
        command: `drivegate probe --port ${port} --try-bauds`,
        after: '(with drivegate stopped) finds the drives on the line and their baud rate.',
        // Said whole in the text already.
        why: rest !== why ? '' : why };
    }
  }
}

/**
 * How live the plant's data is, as drivegate decides it: the drives whose
 * data is live, those that are not, and the buses that are down (from the
 * drives' freshness and the buses' ports, so a bus without drives counts
 * too). What the header's badge says beside the page's own link.
 */
export function plantLiveness(store) {
  const now = performance.now();
  const down = [];
  for (const b of store.buses.values()) {
    if (b.state === 'down') down.push(b.name);
  }
  const freshness = [...store.drives.values()].map((d) => [d, freshnessOf(d, now).freshness]);
  for (const [d, f] of freshness) {
    if (f === 'bus-down' && d.bus && !down.includes(d.bus)) down.push(d.bus);
  }
  // A drive on a bus known down is not live, even while its last status
  // is still young: the bus's news can come before the drive's.
  const live = freshness.filter(([d, f]) => f === 'live' && !down.includes(d.bus)).length;
  return { drives: store.drives.size, live, notLive: store.drives.size - live, busesDown: down };
}

/** A time the data stopped being live: the time of day today, else the date too. */
function sinceWords(at) {
  const t = new Date(at);
  if (Number.isNaN(t.getTime())) return null;
  return t.toDateString() === new Date().toDateString() ? t.toLocaleTimeString([], { hour12: false }) : dateTime(t);
}

/** The buses of the configured drives, in the drives' order. */
export function busesOf(store) {
  const out = [];
  for (const n of store.order) {
    const d = store.drives.get(n);
    if (d && d.bus && !out.includes(d.bus)) out.push(d.bus);
  }
  return out;
}

/** A drive's recent values for the plots: a window of `seconds`. */
export class History {
  constructor(seconds = 30) {
    this.seconds = seconds;
    this.t = [];
    this.speed = [];
    this.position = [];
    this.current = [];
    this.temperature = [];
  }

  push(t, s) {
    this.t.push(t);
    this.speed.push(s.speed_rpm);
    this.position.push(positionTurns(s));
    this.current.push(s.current_a);
    this.temperature.push(s.temperature_c);
    const cut = this.t.findIndex((x) => x >= t - this.seconds);
    if (cut > 0) {
      for (const a of [this.t, this.speed, this.position, this.current, this.temperature]) a.splice(0, cut);
    }
  }
}

/**
 * The position as one number of output turns: whole turns (a 16-bit
 * counter, read as signed so a joint just below zero is -1, not 65535) plus
 * the angle within the turn.
 */
export function positionTurns(s) {
  const turns = s.turns >= 32768 ? s.turns - 65536 : s.turns;
  return turns + s.angle_deg / 360;
}

/** The position as every page writes it: output turns, to a hundredth. */
export function positionText(s) {
  return s ? `${positionTurns(s).toFixed(2)} turns` : '–';
}
