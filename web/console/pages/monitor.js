// The bus monitor: every frame on the wire of a bus, live, newest first,
// with its meaning, CRC, outcome, the silence before it and who caused it. The filters
// are the API's own (the list is reloaded from the bus's ring through
// them); pause holds the list still while frames keep being counted;
// downloads are the API's CSV and PCAP. The list keeps the newest ROWS
// rows, so a page left open for days does not grow.

import { ApiError, busPath, download, get, streamProtocols } from '../api.js';
import { h, fmt, clock, Note, run } from '../ui.js';
import { busesOf } from '../store.js';

export const page = {
  id: 'monitor',
  title: 'Bus monitor',
  nav: { path: '/monitor', label: 'Monitor', key: 'm' },
  match: (path) => {
    if (path === '/monitor') return {};
    const m = /^\/monitor\/([^/]+)$/.exec(path);
    return m ? { bus: decodeURIComponent(m[1]) } : null;
  },
  mount,
};

/** Rows the list keeps (the newest). */
export const ROWS = 500;
/** Frames asked of the ring at each (re)connection. */
const BACKLOG = ROWS;
/**
 * The list moves at most this often: faster than anyone reads it, and each
 * move lays out the list again (the feed brings frames every 50 ms).
 */
const DRAW_MS = 200;

const FUNCTIONS = {
  1: 'read coils', 2: 'read discrete inputs', 3: 'read holding registers', 4: 'read input registers',
  5: 'write single coil', 6: 'write single register', 8: 'diagnostics', 15: 'write multiple coils',
  16: 'write multiple registers', 17: 'report server id', 23: 'read/write registers',
};
const OUTCOMES = [
  ['', 'all outcomes'], ['timeout,crc_error,bad_reply', 'failures (timeout, CRC, bad reply)'], ['retry', 'retries'],
  ['ok', 'ok'], ['exception', 'exception'], ['timeout', 'timeout'], ['crc_error', 'CRC error'], ['bad_reply', 'bad reply'],
  ['sent', 'sent (requests)'], ['broadcast', 'broadcast'], ['stray', 'stray bytes'],
];
const SOURCES = [
  ['', 'every source'], ['poller', 'the poller'], ['scope', 'a scope capture'], ['http', 'HTTP (REST)'],
  ['websocket', 'WebSocket'], ['modbus-tcp', 'Modbus TCP'], ['lease-expiry', 'a lease expiry'],
  ['shutdown', 'the shutdown'], ['internal', 'drivegate itself'],
];
const BAD = new Set(['timeout', 'crc_error', 'bad_reply']);
const WARN = new Set(['exception', 'stray']);
const ARROW = { request: '→', reply: '←', noise: '~' };

function mount(main, params, ctx) {
  const { store, navigate } = ctx;
  const buses = busesOf(store);
  const bus = params.bus || buses[0];
  if (!bus || !buses.includes(bus)) {
    main.append(h('section', { class: 'panel' }, h('h1', {}, 'Bus monitor'),
      h('p', { role: 'alert' }, bus ? `No bus named "${bus}" is configured.` : 'No bus is configured.')));
    return null;
  }
  const drives = store.order.map((n) => store.drives.get(n)).filter((d) => d && d.bus === bus);
  const nameOf = new Map(drives.map((d) => [d.unit, d.name]));
  const stats = { received: 0, rendered: 0, dropped: 0, lost: 0, draws: 0, connections: 0 };
  store.stats.monitor = stats;

  // Filters: the API's, on units, functions, outcomes, sources and who.
  const busSelect = h('select', { 'aria-label': 'Bus', dataset: { filter: 'bus' } },
    buses.map((b) => h('option', { value: b, selected: b === bus }, b)));
  busSelect.addEventListener('change', () => navigate(`/monitor/${encodeURIComponent(busSelect.value)}`));
  const unit = h('select', { 'aria-label': 'Unit', dataset: { filter: 'unit' } },
    h('option', { value: '' }, 'all units'), drives.map((d) => h('option', { value: String(d.unit) }, `${d.unit} ${d.name}`)),
    h('option', { value: '0' }, '0 broadcast'));
  const fn = h('select', { 'aria-label': 'Function', dataset: { filter: 'function' } },
    h('option', { value: '' }, 'all functions'),
    Object.entries(FUNCTIONS).map(([code, name]) => h('option', { value: code }, `${hex(Number(code))} ${name}`)));
  const outcome = h('select', { 'aria-label': 'Outcome', dataset: { filter: 'outcome' } }, OUTCOMES.map(([v, l]) => h('option', { value: v }, l)));
  const source = h('select', { 'aria-label': 'Source', dataset: { filter: 'source' } }, SOURCES.map(([v, l]) => h('option', { value: v }, l)));
  const who = h('input', { type: 'search', 'aria-label': 'Client', placeholder: 'client: token name, address:port', dataset: { filter: 'who' } });
  const pause = h('button', { type: 'button', 'aria-pressed': 'false', dataset: { action: 'pause' } }, 'Pause');
  const filterNote = new Note();
  const conn = h('span', { class: 'conn connecting', role: 'status', dataset: { feed: 'connecting' } }, 'connecting…');
  const count = h('p', { class: 'count', role: 'status' });
  const ring = h('p', { class: 'hint' });

  const csv = h('button', { type: 'button', dataset: { read: 'csv', download: 'csv' } }, 'Download CSV');
  const pcap = h('button', { type: 'button', dataset: { read: 'pcap', download: 'pcap' } }, 'Download PCAP');
  const downloadNote = new Note();
  csv.addEventListener('click', () => run(csv, downloadNote, 'downloading…',
    () => download(busPath(bus, `/monitor/frames.csv${query('?')}`)), (r) => `${r.name}: ${fmt(r.bytes / 1024, 1)} KB`));
  pcap.addEventListener('click', () => run(pcap, downloadNote, 'downloading…',
    () => download(busPath(bus, `/monitor/frames.pcap${query('?')}`)), (r) => `${r.name}: ${fmt(r.bytes / 1024, 1)} KB`));

  // A list of rows in ARIA table roles rather than a <table>: each row is
  // its own box that the browser lays out (and skips while off screen) on
  // its own, so a new row costs the same with 50 or 500 below it.
  const tbody = h('div', { class: 'frame-rows', role: 'rowgroup' });
  main.append(h('section', { class: 'panel monitor' },
    h('h1', {}, 'Bus monitor ', h('span', { class: 'small' }, 'bus '), buses.length > 1 ? h('span', { class: 'filters' }, busSelect) : bus, ' ', conn),
    h('p', { class: 'hint' }, 'Every frame on the wire, newest first, with who caused it. ',
      `The list keeps the newest ${ROWS}; the bus keeps more (download them).`),
    ring,
    h('div', { class: 'row filters' }, unit, fn, outcome, source, who, pause),
    filterNote.el,
    count,
    h('div', { class: 'scroll' }, h('div', { class: 'frames', role: 'table', 'aria-label': 'Frames, newest first' },
      h('div', { role: 'rowgroup', class: 'frame-head' }, h('div', { role: 'row', class: 'frame' }, ['Time', 'Dir', 'Unit', 'Function', 'Meaning', 'Bytes', 'CRC', 'Outcome', 'Silence before', 'Caused by']
        .map((t) => h('span', { role: 'columnheader' }, t)))),
      tbody)),
    h('div', { class: 'row filters' }, csv, pcap, downloadNote.el),
    h('p', { class: 'hint' }, 'Open the PCAP with Wireshark or tshark, which decode it as Modbus RTU once told its UDP port: ',
      h('code', { dataset: { hint: 'tshark' } }, `tshark -r ${bus}-frames.pcap -o mbrtu.udp.port:502`),
      '. Timeouts have no bytes and are only in the CSV.')));

  /** The filter as the API's query (`?unit=1&source=http`), or ''. */
  function query(lead) {
    const q = new URLSearchParams();
    for (const [k, el] of [['unit', unit], ['function', fn], ['outcome', outcome], ['source', source], ['who', who]]) {
      const v = el.value.trim();
      if (v) q.set(k, v);
    }
    const s = q.toString();
    return s ? `${lead}${s}` : '';
  }

  // The list: frames wait in `queue` (the newest ROWS at most) until the
  // next animation frame draws them; while paused they only wait.
  let queue = [];
  let paused = false;
  let pausedAt = 0;
  let frame = 0;
  let ws = null;
  let timer = null;
  let gone = false;
  let delay = 500;
  let generation = 0;

  // The silence before a frame: a request's as drivegate left it (t3.5, or
  // the drive's learned gap), a reply's turnaround.
  const silence = (f) => {
    const us = f.silence_us ?? f.turnaround_us;
    return us === null || us === undefined ? '' : `${fmt(us / 1000, 2)} ms`;
  };

  const row = (f) => {
    if (f.lostHere) {
      return h('div', { role: 'row', class: 'frame lost', dataset: { lost: String(f.lostHere) } },
        h('span', { role: 'cell' }, `${f.lostHere} frames lost here: this page read more slowly than the bus`));
    }
    const retry = f.attempt > 1 ? ` (retry ${f.attempt - 1})` : '';
    const cls = BAD.has(f.outcome) ? 'bad' : (WARN.has(f.outcome) || f.attempt > 1) ? 'warn' : '';
    return h('div', { role: 'row', class: `frame ${cls}`, dataset: { seq: String(f.seq), source: f.source, who: f.source_who || '', outcome: f.outcome, unit: String(f.unit) } },
      h('span', { role: 'cell' }, h('time', { datetime: f.time }, timeUs(f.time_us))),
      h('span', { role: 'cell', title: f.direction }, `${ARROW[f.direction] || ''} ${f.direction}`),
      h('span', { role: 'cell' }, f.unit === 0 ? '0 all' : `${f.unit}${nameOf.has(f.unit) ? ` ${nameOf.get(f.unit)}` : ''}`),
      h('span', { role: 'cell', title: FUNCTIONS[f.function] || '' }, f.function === null || f.function === undefined ? '–' : hex(f.function)),
      h('span', { role: 'cell', title: f.meaning }, f.meaning),
      h('span', { role: 'cell', class: 'bytes', title: `${f.length} bytes, ${f.wire_us} µs on the wire` }, f.bytes),
      h('span', { role: 'cell', class: f.crc === 'bad' ? 'bad' : '' }, f.crc),
      h('span', { role: 'cell', title: f.detail || '' }, `${f.outcome.replaceAll('_', ' ')}${retry}${f.detail ? `: ${f.detail}` : ''}`),
      h('span', { role: 'cell', class: 'num', title: f.direction === 'reply' ? 'the drive\'s turnaround' : 'the silence drivegate left before this request' }, silence(f)),
      h('span', { role: 'cell', title: f.source_text }, f.source_text));
  };

  function showCount() {
    const lost = stats.lost ? `, ${stats.lost} lost (this page read more slowly than the bus)` : ', none lost';
    const held = paused ? `; paused: ${stats.received - pausedAt} frames arrived since, the list resumes with the newest` : '';
    count.textContent = `${stats.received} frames received live${lost}; ${tbody.childElementCount} rows shown${held}`;
    count.classList.toggle('bad', stats.lost > 0);
  }

  function draw() {
    frame = 0;
    if (paused || queue.length === 0) { showCount(); return; }
    const batch = queue;
    queue = [];
    const fragment = document.createDocumentFragment();
    for (let i = batch.length - 1; i >= 0; i -= 1) fragment.append(row(batch[i]));
    tbody.prepend(fragment);
    stats.rendered += batch.length;
    while (tbody.childElementCount > ROWS) tbody.lastElementChild.remove();
    stats.draws += 1;
    showCount();
  }
  let lastDraw = 0;
  let wait = 0;
  const schedule = () => {
    if (frame || wait || paused) return;
    const due = lastDraw + DRAW_MS - performance.now();
    if (due > 0) {
      wait = setTimeout(() => { wait = 0; schedule(); }, due);
      return;
    }
    frame = requestAnimationFrame((t) => { lastDraw = performance.now(); draw(t); });
  };

  function take(frames) {
    for (const f of frames) queue.push(f);
    if (queue.length > ROWS) {
      const cut = queue.length - ROWS;
      stats.dropped += queue.splice(0, cut).filter((f) => !f.lostHere).length;
    }
    schedule();
  }

  pause.addEventListener('click', () => {
    paused = !paused;
    pause.setAttribute('aria-pressed', String(paused));
    pause.textContent = paused ? 'Resume' : 'Pause';
    if (paused) {
      pausedAt = stats.received;
      if (frame) { cancelAnimationFrame(frame); frame = 0; }
      if (wait) { clearTimeout(wait); wait = 0; }
    } else {
      schedule();
    }
    showCount();
  });

  /**
   * (Re)connects: the newest frames that pass the filter from the ring
   * (GET .../frames, which also checks the filter and says what is wrong
   * with it), then the live feed with the same filter. Frames the feed
   * sends again are skipped by their sequence number.
   */
  async function connect() {
    clearTimeout(timer);
    const mine = ++generation;
    if (ws) { const old = ws; ws = null; old.close(1000, 'filter changed'); }
    setConn('connecting', 'connecting…');
    let initial;
    try {
      initial = await get(busPath(bus, `/monitor/frames?limit=${BACKLOG}${query('&')}`));
    } catch (e) {
      if (mine !== generation || gone) return;
      if (e instanceof ApiError && e.status > 0 && e.status < 500 && e.status !== 401) {
        // The filter or the monitor refused: say so, and wait for a change.
        filterNote.fail(e);
        setConn('closed', 'not connected');
        return;
      }
      retry();
      return;
    }
    if (mine !== generation || gone) return;
    filterNote.clear();
    queue = [];
    tbody.replaceChildren();
    let next = initial.next;
    take(initial.frames);
    const scheme = location.protocol === 'https:' ? 'wss' : 'ws';
    const q = `backlog=${BACKLOG}${query('&')}`;
    const socket = new WebSocket(`${scheme}://${location.host}${busPath(bus, '/monitor/live')}?${q}`, streamProtocols());
    ws = socket;
    socket.onopen = () => {
      delay = 500;
      stats.connections += 1;
      setConn('open', 'live');
    };
    socket.onmessage = (event) => {
      let m;
      try { m = JSON.parse(event.data); } catch { return; }
      if (m.type === 'frames') {
        const fresh = m.frames.filter((f) => f.seq >= next);
        if (fresh.length) next = fresh[fresh.length - 1].seq + 1;
        stats.received += fresh.length;
        stats.lost = (stats.lost - (socket.lostTotal || 0)) + m.lost_total;
        socket.lostTotal = m.lost_total;
        if (m.lost > 0) fresh.unshift({ lostHere: m.lost });
        take(fresh);
        if (paused) showCount();
      } else if (m.type === 'error') {
        filterNote.fail(new ApiError(m.problem || { detail: 'refused' }, 400));
      }
    };
    socket.onclose = (event) => {
      if (ws !== socket) return;
      ws = null;
      setConn('closed', event.code === 1001 ? 'drivegate is stopping; reconnecting' : 'connection lost; reconnecting');
      retry();
    };
  }

  function retry() {
    if (gone) return;
    clearTimeout(timer);
    timer = setTimeout(connect, delay);
    delay = Math.min(delay * 2, 5000);
  }

  function setConn(state, text) {
    conn.className = `conn ${state}`;
    conn.dataset.feed = state;
    conn.textContent = text;
  }

  for (const el of [unit, fn, outcome, source, who]) el.addEventListener('change', () => connect());

  get(busPath(bus, '/monitor')).then((m) => {
    ring.textContent = m.enabled
      ? `The bus keeps its last ${m.ring_frames} frames (${fmt(m.memory_bytes / 1e6, 1)} MB); ${m.frames_seen} seen since drivegate started.`
      : 'The bus monitor is off ([monitor] enabled = false): no frames are kept.';
  }).catch((e) => filterNote.fail(e));
  connect();
  showCount();

  return () => {
    gone = true;
    clearTimeout(timer);
    if (frame) cancelAnimationFrame(frame);
    clearTimeout(wait);
    if (ws) { const old = ws; ws = null; old.close(1000, 'page closed'); }
    delete store.stats.monitor;
  };
}

function hex(n) {
  return `0x${n.toString(16).toUpperCase().padStart(2, '0')}`;
}

/** A time of day with µs, from µs since 1970. */
function timeUs(us) {
  return `${clock(Math.floor(us / 1000))}${String(us % 1000).padStart(3, '0')}`;
}
