// drivegate's alarms as the page knows them: GET /api/v1/alarms (date and
// time, drive, kind, text, what to do, active or cleared, who
// acknowledged it and when), read again whenever the stream says one was
// raised, cleared or acknowledged. The daemon keeps them across restarts;
// the page keeps nothing of its own, so every tab shows the same list.

import { ApiError, get, post } from './api.js';

/** Stream messages that change the list. */
export const ALARM_MESSAGES = ['alarm-raised', 'alarm-cleared', 'alarm-acknowledged'];

/** The alarm a stream message carries (nested or flattened). */
export const alarmOf = (m) => (m && m.alarm && typeof m.alarm === 'object' ? m.alarm : m);

export class Alarms {
  constructor(stream) {
    this.stream = stream;
    /** Newest first, as the API lists them. */
    this.list = [];
    this.active = 0;
    this.unacknowledged = 0;
    /** null until read; false when this drivegate has no alarms API. */
    this.available = null;
    this.error = null;
    this.listeners = new Set();
    this.reading = null;
    this.again = false;
    this.newsListeners = new Set();
    for (const type of ALARM_MESSAGES) {
      stream.on(type, (m) => {
        this.refresh();
        const a = alarmOf(m);
        for (const fn of this.newsListeners) fn(type, a);
      });
    }
    // Whatever happened while the connection was down is in the list.
    stream.on('state', (s) => { if (s.state === 'open') this.refresh(); });
  }

  /** Reads the list; a read asked for meanwhile runs once after it. */
  refresh() {
    if (this.reading) { this.again = true; return this.reading; }
    this.reading = get('/api/v1/alarms')
      .then((r) => {
        this.list = r.alarms || [];
        this.active = r.active ?? this.list.filter((a) => a.active).length;
        this.unacknowledged = r.unacknowledged ?? this.list.filter((a) => !a.acknowledged).length;
        this.available = true;
        this.error = null;
      })
      .catch((e) => {
        if (e instanceof ApiError && e.status === 404) this.available = false;
        else this.error = e;
      })
      .finally(() => {
        this.reading = null;
        for (const fn of this.listeners) fn();
        if (this.again) { this.again = false; this.refresh(); }
      });
    return this.reading;
  }

  /** Acknowledges alarm `id` (operator); resolves with the alarm. */
  async acknowledge(id) {
    const a = await post(`/api/v1/alarms/${encodeURIComponent(id)}/ack`);
    await this.refresh();
    return a;
  }

  /** `fn()` after every read of the list. */
  subscribe(fn) {
    this.listeners.add(fn);
    return () => this.listeners.delete(fn);
  }

  /** `fn(type, alarm)` for every alarm message of the stream. */
  onNews(fn) {
    this.newsListeners.add(fn);
    return () => this.newsListeners.delete(fn);
  }
}

/**
 * The active alarms of `drive`, newest first, or null when this
 * drivegate has no alarms API (an older daemon).
 */
export async function activeAlarmsOf(drive) {
  try {
    const r = await get(`/api/v1/alarms?active=true&drive=${encodeURIComponent(drive)}`);
    return (r.alarms || []).filter((a) => a.drive === drive && a.active);
  } catch (e) {
    if (e instanceof ApiError && e.status === 404 && !(e.problem && e.problem.type && e.problem.type.endsWith('unknown-drive'))) return null;
    throw e;
  }
}

/** What an alarm is about, as its list and banner name it. */
export function subjectOf(a) {
  if (a.kind === 'certificate-expiring') return 'gateway';
  return a.drive || `bus ${a.bus}`;
}

/** An alarm's text beside its subject: the text names its subject first
 * ("bus line1: its port failed ...") for the faces that show it alone. */
export function textBeside(a) {
  const prefix = `${subjectOf(a)}: `;
  const text = String(a.text || '');
  return text.startsWith(prefix) ? text.slice(prefix.length) : text;
}

/** An alarm's kind in words. */
export function kindWords(kind) {
  return {
    fault: 'fault', stall: 'stall', offline: 'offline', 'never-answered': 'never answered', 'bus-down': 'bus down',
    'comm-loss': 'communication lost', 'stop-failed': 'stop not confirmed', 'refused-write': 'write refused',
    'certificate-expiring': 'certificate expiring',
  }[kind] || String(kind || '').replaceAll('-', ' ');
}
