// The event log: faults, stalls, offline/online, bus up/down, lease ends
// and every write (who, what, the drive's answer) since this page was
// opened, newest first, filterable by drive, kind and text.

import { h, timeEl } from '../ui.js';

export const page = {
  id: 'events',
  title: 'Events',
  nav: { path: '/events', label: 'Events', key: 'e' },
  match: (path) => (path === '/events' ? {} : null),
  mount,
};

const KINDS = [
  ['', 'all kinds'], ['fault', 'faults'], ['stall', 'stalls'], ['link', 'online / offline'],
  ['alarm', 'alarms'], ['settings', 'settings'], ['lease', 'lease ends'], ['write', 'writes'], ['bus', 'bus'], ['state', 'activation and mode'], ['brake', 'brake'],
];
const SHOWN = 500;

function mount(main, _params, { store }) {
  const drive = h('select', { 'aria-label': 'Drive', dataset: { filter: 'drive' } },
    h('option', { value: '' }, 'all drives'), store.order.map((n) => h('option', { value: n }, n)));
  const kind = h('select', { 'aria-label': 'Kind', dataset: { filter: 'kind' } }, KINDS.map(([v, l]) => h('option', { value: v }, l)));
  const text = h('input', { type: 'search', placeholder: 'search (who, what, answer)', 'aria-label': 'Search', dataset: { filter: 'text' }, 'aria-keyshortcuts': '/' });
  const count = h('span', { class: 'count', role: 'status' });
  const tbody = h('tbody');
  main.append(h('section', { class: 'panel' },
    h('h1', {}, 'Events'),
    h('p', { class: 'hint' }, 'Since this page was opened. Writes come from every client and face (REST, stream, Modbus TCP) and from drivegate itself (lease stops, shutdown). Faults, stalls, drives offline and the other alarms are kept by drivegate across restarts: ',
      h('a', { href: '#/alarms' }, 'see Alarms'), '.'),
    h('div', { class: 'row filters' }, drive, kind, text, count),
    h('div', { class: 'scroll' }, h('table', { class: 'log' },
      h('thead', {}, h('tr', {}, h('th', { scope: 'col' }, 'Time'), h('th', { scope: 'col' }, 'Kind'), h('th', { scope: 'col' }, 'Drive'),
        h('th', { scope: 'col' }, 'Who'), h('th', { scope: 'col' }, 'What'))),
      tbody))));

  const matches = (e) => (!drive.value || e.drive === drive.value)
    && (!kind.value || e.kind === kind.value)
    && (!text.value || `${e.who || ''} ${e.text} ${e.drive || ''}`.toLowerCase().includes(text.value.toLowerCase()));
  const row = (e) => h('tr', { class: e.severity, dataset: { kind: e.kind } },
    h('td', {}, timeEl(e.at)),
    h('td', {}, e.kind), h('td', {}, e.drive || e.bus || '–'), h('td', {}, e.who || '–'), h('td', {}, e.text));
  let shown = 0;
  const render = () => {
    const list = store.events.filter(matches);
    const newest = list.slice(-SHOWN).reverse();
    tbody.replaceChildren(...newest.map(row));
    shown = newest.length;
    count.textContent = `${list.length} of ${store.events.length} events${list.length > SHOWN ? ` (newest ${SHOWN} shown)` : ''}`;
  };
  for (const el of [drive, kind]) el.addEventListener('change', render);
  text.addEventListener('input', render);
  const off = store.onEvent((e) => {
    if (!matches(e)) {
      count.textContent = `${store.events.filter(matches).length} of ${store.events.length} events`;
      return;
    }
    tbody.prepend(row(e));
    shown += 1;
    if (shown > SHOWN) { tbody.lastChild.remove(); shown -= 1; }
    count.textContent = `${store.events.filter(matches).length} of ${store.events.length} events`;
  });
  const slash = (e) => {
    if (e.key === '/' && !e.target.closest('input, textarea, select') && !document.querySelector('dialog[open]')) {
      e.preventDefault();
      text.focus();
    }
  };
  document.addEventListener('keydown', slash);
  render();
  return () => { off(); document.removeEventListener('keydown', slash); };
}
