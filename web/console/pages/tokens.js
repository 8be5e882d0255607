// API tokens (admin): each token in force with its role, where it is
// defined and when it was last used; a new token made as `drivegate token
// new` makes one (shown once, with a copy button; what the first token
// changes for this machine said before it is made), written into the
// configuration file and reloaded; a token revoked the same way.

import { ApiError, del, get, post, setToken, token } from '../api.js';
import { h, Note, run, confirmDialog } from '../ui.js';
import { tabs, reloadAnswer, copyText, saveText, when } from '../gateway.js';

export const page = {
  id: 'tokens',
  title: 'API tokens',
  role: 'admin',
  navAs: 'config',
  match: (path) => (path === '/tokens' ? {} : null),
  mount,
};

const ROLES = [
  ['viewer', 'viewer: reads and the live stream'],
  ['operator', 'operator: runs the machine (setpoints, modes, brake)'],
  ['admin', 'admin: commissioning and this gateway’s settings'],
];

function mount(main, _params, { store }) {
  const s = { list: null, gone: false };
  const tbody = h('tbody');
  const listNote = new Note();
  const name = h('input', { type: 'text', id: 'token-name', autocomplete: 'off', maxlength: 64, dataset: { field: 'token-name' } });
  const role = h('select', { id: 'token-role', dataset: { field: 'token-role' } }, ROLES.map(([v, l]) => h('option', { value: v }, l)));
  const make = h('button', { type: 'button', class: 'primary', dataset: { action: 'make-token' } }, 'Make the token');
  const before = h('div', { class: 'before-token', dataset: { field: 'consequence' } });
  const made = h('div', { class: 'made-token', 'aria-live': 'polite' });
  const makeNote = new Note();
  main.append(h('section', { class: 'panel tokens-page' },
    tabs('tokens'),
    h('h1', {}, 'API tokens'),
    h('p', { class: 'hint' }, 'Every client of the API and of this console presents a token (Authorization: Bearer); its role decides what it may do, and its name is who the audit log says did it. The configuration file holds each token’s SHA-256, never the token.'),
    listNote.el,
    h('div', { class: 'scroll' }, h('table', { class: 'log tokens' },
      h('thead', {}, h('tr', {}, ['Name', 'Role', 'Defined', 'Last used', ''].map((t) => h('th', { scope: 'col' }, t)))),
      tbody)),
    h('h2', {}, 'Make a token'),
    h('div', { class: 'row' },
      h('label', { class: 'field', for: 'token-name' }, h('span', {}, 'Name (letters, digits, - _ .)'), name),
      h('label', { class: 'field', for: 'token-role' }, h('span', {}, 'Role'), role),
      make),
    before, makeNote.el, made));

  const consequence = () => {
    const l = s.list;
    if (!l) return;
    const parts = [h('p', {}, 'The token is shown once, when it is made: copy it then. The file keeps only its SHA-256.')];
    if (l.first_token) {
      parts.push(h('p', { class: 'note warn', dataset: { note: 'first-token' } },
        'This will be the first token. ', l.first_token,
        ' This page then uses the new token' + (role.value === 'admin' ? '.' : `, and keeps only the ${role.value} role’s controls.`)));
    }
    if (l.no_admin && role.value !== 'admin') {
      parts.push(h('p', { class: 'note warn', dataset: { note: 'no-admin' } }, 'No token has the admin role: ', l.no_admin));
    }
    if (!l.writable) {
      parts.push(h('p', { class: 'note warn' }, `drivegate may not write ${l.file}: the new file is offered to download, to put in place by hand.`));
    }
    before.replaceChildren(...parts);
  };
  role.addEventListener('change', consequence);

  const revoke = async (t) => {
    const mine = store.me.who === t.name;
    const last = s.list.tokens.length === 1;
    const answer = await confirmDialog({
      title: `Revoke the token “${t.name}”?`,
      body: [
        `Its [[http.token]] is removed from ${s.list.file} and the file reloaded: the ${t.role} token “${t.name}” is refused from the next request on.`,
        mine ? h('p', { class: 'note warn' }, 'It is the token this page uses: the page will ask for another.') : null,
        last ? h('p', { class: 'note warn' }, 'It is the last token: the API then listens on this machine (loopback) only, and every client on it is admin without a token.') : null,
      ].filter(Boolean),
      confirm: 'Revoke',
      danger: true,
    });
    if (!answer.ok) return;
    const r = await run(null, listNote, `revoking “${t.name}”…`, () => del(`/api/v1/tokens/${encodeURIComponent(t.name)}`),
      (r) => `“${r.name}” revoked${r.notes.length ? `: ${r.notes.join('; ')}` : ''}`);
    if (r) {
      made.replaceChildren(reloadAnswer(r.reload));
      if (mine) { setToken(null); }
      await refresh();
    }
  };

  const draw = () => {
    const l = s.list;
    tbody.replaceChildren(...(l.tokens.length ? l.tokens.map((t) => {
      const button = h('button', { type: 'button', class: 'danger', dataset: { revoke: t.name } }, 'Revoke…');
      button.addEventListener('click', () => revoke(t));
      return h('tr', { dataset: { token: t.name } },
        h('td', {}, h('strong', {}, t.name), store.me.who === t.name ? h('small', {}, ' (this page’s)') : null),
        h('td', {}, h('span', { class: `role ${t.role}` }, t.role)),
        h('td', {}, t.defined),
        h('td', { dataset: { field: 'last-used' } }, when(t.last_used)),
        h('td', {}, button));
    }) : [h('tr', {}, h('td', { colspan: 5 }, 'No token is configured: the API listens on this machine (loopback) only, and every client on it is admin.'))]));
    consequence();
  };

  const refresh = async () => {
    try {
      s.list = await get('/api/v1/tokens');
      if (s.gone) return;
      listNote.clear();
      draw();
    } catch (e) {
      listNote.fail(e);
    }
  };

  make.addEventListener('click', async () => {
    const wanted = { name: name.value.trim(), role: role.value };
    const first = !!(s.list && s.list.first_token);
    const r = await run(make, makeNote, `making the token “${wanted.name}”…`, () => post('/api/v1/tokens', wanted),
      (r) => (r.reload ? `made, written into the file and reloaded: “${r.name}” (${r.role}) works from now on` : `made, but not written: ${r.not_written}`));
    if (!r) return;
    name.value = '';
    const field = h('input', { type: 'text', readonly: true, class: 'secret', value: r.token, 'aria-label': 'The new token', dataset: { field: 'new-token' } });
    const copy = h('button', { type: 'button', class: 'primary', dataset: { action: 'copy-token' } }, 'Copy');
    const copied = new Note();
    copy.addEventListener('click', async () => {
      if (await copyText(r.token, field)) copied.ok('copied');
      else copied.fail(new Error('the browser did not let the page copy: select the token and copy it by hand'));
    });
    const box = [
      h('h3', {}, `The token “${r.name}” (${r.role})`),
      h('p', { class: 'note warn' }, 'Shown this once: copy it now and give it to its client. It is not kept anywhere; if it is lost, revoke it and make another.'),
      h('div', { class: 'row' }, field, copy, copied.el),
      h('p', { class: 'hint' }, 'A client sends it as ', h('code', {}, 'Authorization: Bearer <token>'), '.'),
    ];
    if (r.not_written) {
      const save = h('button', { type: 'button', dataset: { action: 'download' } }, 'Download the new file');
      save.addEventListener('click', () => saveText((s.list.file || 'drivegate.toml').split('/').pop(), r.file_text));
      box.push(h('p', { class: 'note warn' }, r.not_written), h('pre', { class: 'toml' }, r.lines), save);
    } else if (r.reload) {
      box.push(reloadAnswer(r.reload));
    }
    if (first && r.reload) {
      const use = h('button', { type: 'button', class: 'primary', dataset: { action: 'use-token' } }, 'Use it for this page');
      use.addEventListener('click', () => { setToken(r.token); location.reload(); });
      box.push(h('p', {}, 'From now on this page needs a token too: it uses this one once you have copied it.'), use);
      // Until then the page keeps working with the token it is given.
      if (!token()) setToken(r.token);
    }
    made.replaceChildren(...box);
    field.select();
    await refresh();
  });

  refresh().catch((e) => { if (!(e instanceof ApiError)) throw e; });
  return () => { s.gone = true; };
}
