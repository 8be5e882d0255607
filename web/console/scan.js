// Commissioning steps shared by its pages. A bus scan in steps (POST /api/v1/buses/{bus}/scan over a few units at
// a time), so a page can show its progress and stop it between steps; and
// the rule a scan must meet before an address broadcast is offered: the
// whole range 1 to 255 read, exactly one drive answering, no garbled
// reply (two drives at one address), nothing left unread.

import { busPath, post } from './api.js';
import { h } from './ui.js';

/** Units per scan request: the progress moves after each. */
export const SCAN_CHUNK = 8;

/**
 * Scans units `from` to `to` of `bus`. `progress(found, done, total)` is
 * told after each step; `stop()` returning true ends it between steps.
 * Resolves with what was found ({bus, from, to, answered, garbled,
 * missing, silent, not_scanned, complete}); rejects with the API's error.
 */
export async function scanBus(bus, from, to, { progress = () => {}, stop = () => false } = {}) {
  const found = { bus, from, to, answered: [], garbled: [], missing: [], silent: 0, not_scanned: [], complete: false };
  const total = Math.max(1, to - from + 1);
  let stopped = false;
  for (let u = from; u <= to; u += SCAN_CHUNK) {
    if (stop()) { stopped = true; break; }
    const last = Math.min(to, u + SCAN_CHUNK - 1);
    const r = await post(busPath(bus, '/scan'), { from: u, to: last });
    found.answered.push(...r.answered);
    found.garbled.push(...r.garbled);
    // A configured drive that is silent is reported by every step.
    for (const m of r.missing) if (!found.missing.includes(m)) found.missing.push(m);
    found.silent += r.silent;
    found.not_scanned.push(...r.not_scanned);
    progress(found, last - from + 1, total);
  }
  found.complete = !stopped;
  return found;
}

/**
 * Whether `scan` allows an address broadcast on `bus`: {ok, text}, the
 * text saying why not in words.
 */
export function broadcastVerdict(scan, bus) {
  const s = scan;
  if (!s || s.bus !== bus) return { ok: false, text: `First scan bus ${bus} over units 1 to 255 with only the new drive connected.` };
  if (!s.complete || s.from !== 1 || s.to !== 255) return { ok: false, text: 'The last scan did not cover units 1 to 255: scan the whole range so no other drive can hide.' };
  if (s.garbled.length) return { ok: false, text: `Garbled replies at ${s.garbled.join(', ')}: two drives share an address. Disconnect all but one.` };
  if (s.not_scanned.length) return { ok: false, text: 'Some units could not be read (bus busy): scan again.' };
  if (s.answered.length !== 1) return { ok: false, text: `The scan found ${s.answered.length} drives answering; the broadcast would re-address all of them. Leave exactly one drive connected.` };
  return { ok: true, text: `The scan found exactly one drive, at unit ${s.answered[0].unit}.` };
}

/**
 * Follows a procedure a drive runs by itself (calibration, fine-tuning)
 * from the statuses the page receives: over once the drive has stood
 * still for half a second, no sooner than three quarters of the time it
 * is expected to take (`expectedS`, or null when unknown), after a fault
 * or a stall, or after a minute. `tick({t, s})` is told every 100 ms.
 * Resolves {t, s}: the seconds it took and the last status.
 */
export function followProcedure(store, name, expectedS, tick = () => {}) {
  return new Promise((resolve) => {
    const started = performance.now();
    let moved = false; let stillSince = null;
    const check = () => {
      const d = store.drives.get(name);
      const s = d && d.status;
      const t = (performance.now() - started) / 1000;
      if (s && s.speed_rpm !== 0) { moved = true; stillSince = null; } else if (stillSince === null) stillSince = t;
      const done = t >= (expectedS || 1) * 0.75 && stillSince !== null && t - stillSince > 0.5 && (moved || t > (expectedS || 8));
      tick({ t, s });
      if (done || t > 60 || (s && (s.fault !== 'none' || s.stalled))) {
        clearInterval(timer);
        resolve({ t, s });
      }
    };
    const timer = setInterval(check, 100);
    check();
  });
}

/** What a scan found, as a table: who answered, garbled replies, units not read. */
export function scanTable(found) {
  const rows = found.answered.map((a) => h('tr', {},
    h('td', {}, a.unit), h('td', {}, a.configured_as || 'not configured'),
    h('td', {}, a.status ? `${a.status.active ? 'active' : 'inactive'}, ${a.status.mode.replaceAll('_', ' ')}, ${a.status.voltage_v} V` : `exception ${a.exception_code}`)));
  for (const u of found.garbled) rows.push(h('tr', { class: 'fault' }, h('td', {}, u), h('td', {}, 'garbled reply'), h('td', {}, 'two drives with one address?')));
  for (const n of found.not_scanned) rows.push(h('tr', { class: 'stalled' }, h('td', {}, n.unit), h('td', {}, 'not read'), h('td', {}, n.reason)));
  return h('div', {},
    found.missing.length ? h('p', { class: 'note fail' }, `Configured but silent: ${found.missing.join(', ')}`) : null,
    h('table', { class: 'kv' }, h('thead', {}, h('tr', {}, h('th', {}, 'Unit'), h('th', {}, 'Drive'), h('th', {}, 'Status'))), h('tbody', {}, rows)));
}
