// Overview: every bus and every drive at a glance, live. A drive in fault,
// stalled, or whose data is not live (stale, offline, never answered, its
// bus down: drivegate's freshness) stands out (colour, and a word, never
// colour alone), its last values greyed;
// rows update in place, only the cells that changed, at most 20 times a
// second (faster than anyone reads, and a quarter of the layout work of
// drawing every frame), so a hundred drives at the bus's full rate cost the
// browser little.

import { h, fmt, age, ago, words, clock } from '../ui.js';
import { positionText, freshnessOf } from '../store.js';

export const page = {
  id: 'overview',
  title: 'Overview',
  nav: { path: '/', label: 'Overview', key: 'o' },
  match: (path) => (path === '/' || path === '' ? {} : null),
  mount,
};

/** What stands out about a drive, worst first: values that are not live first of all. */
export function condition(d, stale) {
  const s = d.status;
  const f = freshnessOf(d, performance.now());
  if (!f.live) return { cls: f.cls, text: f.freshness === 'bus-down' ? 'bus down' : f.freshness === 'never' ? 'never answered' : f.freshness };
  if (!s) return { cls: 'unknown', text: 'no status yet' };
  if (s.fault !== 'none') return { cls: 'fault', text: `fault: ${words(s.fault)}` };
  if (s.stalled) return { cls: 'stalled', text: 'stalled' };
  if (stale) return { cls: 'unknown', text: 'stale' };
  if (!s.active) return { cls: 'inactive', text: 'inactive' };
  return { cls: 'ok', text: s.speed_rpm !== 0 ? 'running' : 'ready' };
}

/**
 * The drives in one line: how many are online (their data live) and what
 * is wrong with the others, a bus down first ("0 of 2 online: bus line1
 * is down"); faults and stalls of live drives after.
 */
export function summaryText(store) {
  let live = 0; let offline = 0; let stale = 0; let never = 0; let faults = 0; let stalls = 0;
  const down = [];
  for (const d of store.drives.values()) {
    const f = freshnessOf(d, performance.now()).freshness;
    if (f === 'live') live += 1;
    else if (f === 'bus-down') { if (!down.includes(d.bus)) down.push(d.bus); }
    else if (f === 'offline') offline += 1;
    else if (f === 'stale') stale += 1;
    else never += 1;
    if (f === 'live' && d.status && d.status.fault !== 'none') faults += 1;
    if (f === 'live' && d.status && d.status.stalled) stalls += 1;
  }
  const parts = [];
  if (down.length === 1) parts.push(`bus ${down[0]} is down`);
  else if (down.length > 1) parts.push(`buses ${down.join(', ')} are down`);
  if (offline) parts.push(`${offline} offline`);
  if (stale) parts.push(`${stale} stale`);
  if (never) parts.push(`${never} never answered (check the bus's baud rate and the drives' unit addresses)`);
  if (faults) parts.push(`${faults} in fault`);
  if (stalls) parts.push(`${stalls} stalled`);
  const head = `${live} of ${store.drives.size} online`;
  return { text: parts.length ? `${head}: ${parts.join(', ')}` : head, bad: parts.length > 0 };
}

/** Shortest time between two draws, ms. */
const DRAW_MS = 50;

const COLUMNS = [
  ['Drive', 'name'], ['Bus / unit', 'where'], ['State', 'state'], ['Mode', 'mode'],
  ['Speed rpm', 'speed', 'num'], ['Position', 'position', 'num'], ['Current A', 'current', 'num'],
  ['Voltage V', 'voltage', 'num'], ['Temp °C', 'temp', 'num'], ['Age', 'age', 'num'],
];

function mount(main, _params, { store }) {
  const summary = h('p', { class: 'summary drives', role: 'status' });
  const buses = h('div', { class: 'buses' });
  const tbody = h('tbody');
  const table = h('table', { class: 'drives' },
    h('caption', { class: 'sr-only' }, 'Drives, live'),
    h('thead', {}, h('tr', {}, COLUMNS.map(([label, , cls]) => h('th', { scope: 'col', class: cls }, label)))),
    tbody);
  // The faces that are not this page's own, from /readyz: the Modbus TCP
  // listener with its connections and the addresses it refused or closed
  // lately, in the daemon's words (docs/modbus-tcp.md); the MQTT link
  // (docs/mqtt.md), shown only with [mqtt]; the OPC UA server
  // (docs/opcua.md), shown only with [opcua].
  const modbus = h('p', { class: 'summary modbus', role: 'status' });
  modbus.hidden = true;
  const refusals = h('div', { class: 'modbus-refusals' });
  const mqtt = h('p', { class: 'summary mqtt', role: 'status' });
  mqtt.hidden = true;
  const opcua = h('p', { class: 'summary opcua', role: 'status' });
  opcua.hidden = true;
  // A face whose task crashed (docs/operations.md): down and when it is
  // started again, or serving again and how often it was; shown only then.
  const crashed = h('p', { class: 'summary faces', role: 'status' });
  crashed.hidden = true;
  main.append(
    h('section', { class: 'panel', 'aria-labelledby': 'buses-h' }, h('h1', { id: 'buses-h' }, 'Buses'), buses, modbus, refusals, mqtt, opcua, crashed),
    h('section', { class: 'panel', 'aria-labelledby': 'drives-h' }, h('h1', { id: 'drives-h' }, 'Drives'), summary,
      h('div', { class: 'scroll' }, table)));

  const rows = new Map();
  const dirty = new Set();
  let all = true;
  let agesDue = false;
  let frame = 0;

  function row(name) {
    let r = rows.get(name);
    if (r) return r;
    const cells = {};
    const tr = h('tr', { dataset: { drive: name } });
    for (const [, key, cls] of COLUMNS) {
      const td = h(key === 'name' ? 'th' : 'td', key === 'name' ? { scope: 'row' } : { class: cls });
      cells[key] = td;
      tr.append(td);
    }
    cells.name.append(h('a', { href: `#/drive/${encodeURIComponent(name)}` }, name));
    r = { tr, cells, text: {} };
    rows.set(name, r);
    return r;
  }

  function set(r, key, text) {
    if (r.text[key] !== text) {
      r.text[key] = text;
      r.cells[key].textContent = text;
      // A narrow window cuts long cells: the whole text on hover.
      if (key === 'state') r.cells[key].title = text;
    }
  }

  function drawDrive(d, now, stale) {
    const r = row(d.name);
    const s = d.status;
    const c = condition(d, stale);
    if (r.tr.className !== c.cls) r.tr.className = c.cls;
    set(r, 'where', `${d.bus} / ${d.unit}`);
    // Values that are not live are the drive's last ones: the row is
    // greyed (CSS) and its state says why and since when (the whole
    // reason on hover).
    const f = freshnessOf(d, now);
    if (r.tr.dataset.link !== (d.link || 'unknown')) r.tr.dataset.link = d.link || 'unknown';
    if (r.tr.dataset.freshness !== f.freshness) r.tr.dataset.freshness = f.freshness;
    set(r, 'state', !f.live ? f.short : c.text + (s && s.active && c.cls !== 'ok' ? ', active' : ''));
    const why = f.live ? '' : f.text + (f.why && !f.text.includes(f.why) ? ` (${f.why})` : '');
    if (r.cells.state.title !== (why || r.text.state)) r.cells.state.title = why || r.text.state;
    set(r, 'mode', s ? words(s.mode) : '–');
    set(r, 'speed', s ? fmt(s.speed_rpm) : '–');
    set(r, 'position', positionText(s));
    set(r, 'current', s ? fmt(s.current_a, 2) : '–');
    set(r, 'voltage', s ? fmt(s.voltage_v) : '–');
    set(r, 'temp', s ? fmt(s.temperature_c) : '–');
    set(r, 'age', d.receivedAt !== undefined ? age(now - d.receivedAt) : '–');
    // For the benchmark: statuses that reached the screen (two arriving
    // between draws count once), and when the first one did.
    if (d.receivedAt !== undefined && r.drawn !== d.receivedAt) {
      r.drawn = d.receivedAt;
      store.stats.rowsDrawn = (store.stats.rowsDrawn || 0) + 1;
    }
    if (s && store.stats.firstRowsAt === undefined) store.stats.firstRowsAt = now;
  }

  /** What the utilisation says, beside it: the share of the wire's time
   * in use, and why 100 % is no fault on a bus polled flat out. */
  function utilisationNote(b) {
    return h('p', { class: 'hint utilisation', dataset: { field: 'utilisation-note' } }, b.polled_flat_out
      ? 'Utilisation is the share of the wire\'s time in use. Its drives are polled as fast as the line allows (poll_interval_ms = 0), so it stays near 100 % by design: commands still go ahead of polls.'
      : 'Utilisation is the share of the wire\'s time in use (frames, silences, waits for replies); near 100 %, commands wait longer.');
  }

  /** A rate of the wire: live only while the port is open. */
  function rate(b, value, text) {
    if (b.state !== 'up') {
      const why = b.state === 'opening' ? 'the port is not open yet' : 'the port is down';
      return h('dd', { class: 'not-live', title: `Not live: ${why}${b.reason ? ` (${b.reason})` : ''}` }, `— not live: ${why}`);
    }
    return h('dd', {}, value === null ? '–' : text);
  }

  function drawBuses() {
    const cards = [];
    for (const b of store.buses.values()) {
      const down = b.state !== 'up';
      cards.push(h('article', { class: `bus ${down ? 'down' : 'up'}`, dataset: { bus: b.name } },
        h('h2', {}, b.name, ' ', h('span', { class: 'badge' }, down ? `port ${b.state}` : 'port up')),
        h('dl', {},
          h('dt', {}, 'Port'), h('dd', {}, `${b.port} @ ${b.baud}`),
          h('dt', {}, 'Drives online'), h('dd', {}, b.drives === 0 ? 'none configured: scan the bus on the commissioning page' : `${b.drives_online} of ${b.drives}`),
          h('dt', {}, 'Utilisation'), rate(b, b.utilisation, `${fmt(b.utilisation * 100)} %`),
          h('dt', {}, 'Errors'), rate(b, b.errorRate, `${fmt(b.errorRate * 100, 2)} % of transactions`),
          h('dt', {}, 'Queue'), h('dd', {}, `${b.queue.emergency} / ${b.queue.command} / ${b.queue.poll}`, h('small', {}, ' emerg. / cmd / poll'))),
        // Why 100 % is no fault says nothing while the port is down.
        down ? null : utilisationNote(b),
        b.reason ? h('p', { class: 'reason' }, b.reason) : null));
    }
    if (store.busesKnown && cards.length === 0) {
      // The package's configuration as shipped: say what to do first.
      cards.push(h('p', { class: 'reason no-bus' }, 'No bus configured: run ',
        h('code', {}, 'drivegate probe --port /dev/serial/by-id/...'),
        ' (your adapter\'s stable name: ls -l /dev/serial/by-id/) to find the drives and their baud rate, then add a [[bus]] with its drives to the configuration and reload it (systemctl reload drivegate).'));
    }
    buses.replaceChildren(...cards);
  }

  function draw() {
    frame = 0;
    store.stats.frames = (store.stats.frames || 0) + 1;
    const now = performance.now();
    const stale = store.stream.state !== 'open';
    if (all) {
      drawBuses();
      const wanted = store.order.map((n) => row(n).tr);
      if (tbody.children.length !== wanted.length || wanted.some((tr, i) => tbody.children[i] !== tr)) {
        tbody.replaceChildren(...wanted);
      }
    }
    const names = all ? store.order : [...dirty];
    for (const name of names) {
      const d = store.drives.get(name);
      if (d) drawDrive(d, now, stale);
    }
    if (agesDue) {
      for (const name of store.order) {
        const d = store.drives.get(name);
        if (d && d.receivedAt !== undefined) {
          set(row(name), 'age', age(now - d.receivedAt));
          if (!freshnessOf(d, now).live) drawDrive(d, now, store.stream.state !== 'open');
        }
      }
      agesDue = false;
    }
    all = false;
    dirty.clear();
    const text = summaryText(store);
    if (summary.textContent !== text.text) {
      summary.textContent = text.text;
      summary.className = `summary drives ${text.bad ? 'bad' : 'good'}`;
    }
  }

  function showModbus(m) {
    modbus.hidden = !m;
    const lines = m ? m.turned_away.map((t) => t.text) : [];
    if (refusals.dataset.lines !== lines.join('\n')) {
      refusals.dataset.lines = lines.join('\n');
      refusals.replaceChildren(...lines.map((text) => h('p', { class: 'summary bad modbus-refused' }, text)));
    }
    if (!m) return;
    const connections = `${m.connections} connection${m.connections === 1 ? '' : 's'}`;
    const text = `Modbus TCP: serving on ${m.listen} (${connections})`;
    if (modbus.textContent !== text) modbus.textContent = text;
    modbus.className = 'summary modbus good';
  }
  function showMqtt(m) {
    mqtt.hidden = !m;
    if (!m) return;
    let text;
    if (!m.connected) text = `MQTT: not connected to ${m.broker}${m.last_error ? ` (${m.last_error})` : ''}`;
    else if (!m.publishing) text = `MQTT: connected to ${m.broker}, waiting for the primary host to be online`;
    else text = `MQTT: publishing to ${m.broker}`;
    if (mqtt.textContent !== text) mqtt.textContent = text;
    mqtt.className = `summary mqtt ${m.connected && m.publishing ? 'good' : 'bad'}`;
  }
  function showOpcUa(o) {
    opcua.hidden = !o;
    if (!o) return;
    const sessions = `${o.sessions} session${o.sessions === 1 ? '' : 's'}`;
    let text;
    if (o.serving) text = `OPC UA: serving on opc.tcp://${o.listen}/ (${sessions})`;
    else if (o.last_error) text = `OPC UA: not serving on ${o.listen} (${o.last_error})`;
    else text = `OPC UA: making its certificate, then serving on opc.tcp://${o.listen}/`;
    if (opcua.textContent !== text) opcua.textContent = text;
    opcua.className = `summary opcua ${o.serving ? 'good' : 'bad'}`;
  }
  function showFaces(faces) {
    const list = faces || [];
    crashed.hidden = list.length === 0;
    if (!list.length) return;
    const text = list.map((f) => (f.serving
      ? `${f.name}: serving again, restarted ${f.restarts} time${f.restarts === 1 ? '' : 's'} (last: ${f.last_crash})`
      : `${f.name}: down since ${clock(new Date(f.down_since))} (${f.down_why}); started again at ${clock(new Date(f.restart_at))}`)).join('. ');
    if (crashed.textContent !== text) crashed.textContent = text;
    crashed.className = `summary faces ${list.some((f) => !f.serving) ? 'bad' : 'good'}`;
  }
  async function pollMqtt() {
    try {
      const r = await fetch('/readyz', { cache: 'no-store', headers: { Accept: 'application/json' } });
      const ready = await r.json();
      showModbus(ready.modbus_tcp);
      showMqtt(ready.mqtt);
      showOpcUa(ready.opcua);
      showFaces(ready.faces);
    } catch {
      // The stream's state already says when drivegate cannot be reached.
    }
  }
  const mqttTimer = setInterval(pollMqtt, 5000);
  pollMqtt();

  let last = 0;
  let timer = 0;
  function schedule() {
    if (frame || timer) return;
    const wait = last + DRAW_MS - performance.now();
    if (wait <= 0) frame = requestAnimationFrame(drawn);
    else timer = setTimeout(() => { timer = 0; frame = requestAnimationFrame(drawn); }, wait);
  }
  function drawn() {
    last = performance.now();
    draw();
  }

  const off = store.subscribe((name) => {
    if (name === null) all = true;
    else dirty.add(name);
    schedule();
  });
  // Ages move on by themselves: redraw every row's age four times a second.
  const ages = setInterval(() => { agesDue = true; schedule(); }, 250);
  draw();
  return () => {
    off();
    clearInterval(ages);
    clearInterval(mqttTimer);
    clearTimeout(timer);
    if (frame) cancelAnimationFrame(frame);
  };
}
