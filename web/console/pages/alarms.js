// Alarms: what drivegate keeps across restarts (faults, stalls, drives
// offline, buses down, communication-loss stops, stops not confirmed,
// writes refused by a safety rule), newest first, with date and time,
// what it means and what to check, active or cleared, and who
// acknowledged it. An operator acknowledges each; the banner in the header
// stays until every alarm is.

import { h, Note, run, timeEl, dateTime } from '../ui.js';
import { kindWords, subjectOf, textBeside } from '../alarms.js';

export const page = {
  id: 'alarms',
  title: 'Alarms',
  nav: { path: '/alarms', label: 'Alarms', key: 'a' },
  match: (path) => (path === '/alarms' ? {} : null),
  mount,
};

const SHOWS = [
  ['all', 'all alarms'], ['unacknowledged', 'not acknowledged'], ['active', 'active'],
];

function mount(main, _params, { store }) {
  const alarms = store.alarms;
  const show = h('select', { 'aria-label': 'Show', dataset: { filter: 'alarms' } }, SHOWS.map(([v, l]) => h('option', { value: v }, l)));
  const count = h('span', { class: 'count', role: 'status' });
  const note = new Note();
  const tbody = h('tbody');
  main.append(h('section', { class: 'panel' },
    h('h1', {}, 'Alarms'),
    h('p', { class: 'hint' }, 'Kept by drivegate across restarts, newest first. An alarm stays active while its condition lasts; acknowledging it says someone has seen it (who and when are kept), it does not clear it.'),
    h('div', { class: 'row filters' }, show, count), note.el,
    h('div', { class: 'scroll' }, h('table', { class: 'log alarms' },
      h('thead', {}, h('tr', {}, ['Raised', 'Drive', 'Alarm', 'What to do', 'State', 'Acknowledged'].map((t) => h('th', { scope: 'col' }, t)))),
      tbody))));

  const row = (a) => {
    const ack = a.acknowledged
      ? h('span', {}, `by ${a.acknowledged_by || '–'}`, h('br'), a.acknowledged_at ? timeEl(a.acknowledged_at) : '')
      : store.can('operator')
        ? h('button', { type: 'button', class: 'primary', dataset: { ack: String(a.id) } }, 'Acknowledge')
        : 'not yet';
    if (ack instanceof HTMLButtonElement) {
      ack.addEventListener('click', () => run(ack, note, `acknowledging alarm ${a.id}…`, () => alarms.acknowledge(a.id),
        (r) => `alarm ${r.id} acknowledged by ${r.acknowledged_by} at ${dateTime(r.acknowledged_at)}`));
    }
    const state = a.active ? h('strong', {}, 'active') : h('span', {}, 'cleared', a.cleared_at ? [h('br'), timeEl(a.cleared_at)] : null);
    return h('tr', { class: `${a.active ? 'bad' : ''} ${a.acknowledged ? 'acked' : 'unacked'}`, dataset: { alarm: String(a.id), kind: a.kind } },
      h('td', {}, timeEl(a.raised_at), a.count > 1 ? h('small', {}, h('br'), `${a.count} times, last ${dateTime(a.last_at)}`) : null),
      h('td', {}, subjectOf(a)),
      h('td', {}, h('span', { class: 'kind' }, kindWords(a.kind)), ' ', textBeside(a)),
      h('td', { class: 'help' }, a.help || '–'),
      h('td', {}, state),
      h('td', {}, ack));
  };
  const render = () => {
    if (alarms.available === false) {
      count.textContent = '';
      tbody.replaceChildren(h('tr', {}, h('td', { colspan: 6 }, 'This drivegate keeps no alarms (it has no /api/v1/alarms).')));
      return;
    }
    if (alarms.error) note.fail(alarms.error);
    const want = show.value;
    const list = alarms.list.filter((a) => want === 'all' || (want === 'active' ? a.active : !a.acknowledged));
    tbody.replaceChildren(...list.map(row));
    count.textContent = `${list.length} shown; ${alarms.active} active, ${alarms.unacknowledged} not acknowledged`;
  };
  show.addEventListener('change', render);
  const off = alarms.subscribe(render);
  render();
  alarms.refresh();
  return () => off();
}
