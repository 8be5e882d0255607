// Certificates (admin): the OPC UA server's own, the client applications
// trusted and refused (and user certificates and issuers where there are
// any), the HTTPS and Modbus/TCP Security certificates: subject, issuer,
// application URI, validity and thumbprint. Trusting a refused client,
// removing a trusted one and renewing the server's certificate take one
// click and a confirmation that names the thumbprint; they apply without
// a restart. A certificate that expires within 30 days is marked (and is
// an alarm).

import { del, get, post } from '../api.js';
import { h, Note, confirmDialog, dateTime } from '../ui.js';
import { tabs, fromNow } from '../gateway.js';

export const page = {
  id: 'certificates',
  title: 'Certificates',
  role: 'admin',
  navAs: 'config',
  match: (path) => (path === '/certificates' ? {} : null),
  mount,
};

/** The groups, in the order shown, with what each is for. */
const GROUPS = [
  ['opcua-server', 'OPC UA server', 'The certificate this gateway presents to OPC UA clients; they trust it once.'],
  ['opcua-rejected', 'OPC UA clients refused', 'Client applications that tried to connect with a certificate nobody trusted yet. Trust the ones you know: their next connection is accepted.'],
  ['opcua-trusted', 'OPC UA clients trusted', 'Client applications whose secure connections are accepted.'],
  ['opcua-user', 'OPC UA user certificates', 'User certificates (X.509 identity tokens) trusted, or the CAs that sign them.'],
  ['opcua-issuer', 'OPC UA issuers', 'CAs of client application certificates.'],
  ['https', 'HTTPS', 'The certificate this API and console are served with.'],
  ['https-client-ca', 'HTTPS client CA', 'The CA whose client certificates HTTPS accepts.'],
  ['modbus-tls', 'Modbus/TCP Security', 'The certificate the Modbus/TCP Security listener presents.'],
  ['modbus-tls-client-ca', 'Modbus/TCP Security client CA', 'The CA whose client certificates (and their role) Modbus/TCP Security accepts.'],
];

/** A thumbprint in pairs, as OPC UA clients show it. */
const pairs = (hex) => hex.match(/.{1,2}/g).join(':');

function mount(main) {
  const s = { gone: false };
  const note = new Note();
  const body = h('div', { class: 'cert-groups' });
  const notes = h('ul', { class: 'remarks' });
  main.append(h('section', { class: 'panel certs-page' },
    tabs('certificates'),
    h('h1', {}, 'Certificates'),
    h('p', { class: 'hint' }, 'What this gateway presents and whom it trusts. A thumbprint is the SHA-1 of the certificate, as OPC UA clients show it: compare it with the one the client’s owner reads on their side before trusting. A certificate that expires within 30 days is marked, and raises an alarm.'),
    note.el, notes, body));

  const act = async (what, cert, call, consequence) => {
    const answer = await confirmDialog({
      title: `${what}?`,
      body: [
        h('p', {}, h('strong', {}, cert.subject)),
        cert.application_uri ? h('p', {}, 'Application URI: ', h('code', {}, cert.application_uri)) : null,
        h('p', {}, 'Thumbprint (SHA-1): ', h('code', { dataset: { field: 'confirm-thumbprint' } }, pairs(cert.thumbprint))),
        consequence,
      ].filter(Boolean),
      confirm: what,
      danger: what.startsWith('Remove'),
    });
    if (!answer.ok) return;
    note.pending(`${what.toLowerCase()}…`);
    try {
      const r = await call();
      note.ok(r.done);
    } catch (e) {
      note.fail(e);
    }
    await refresh();
  };

  const row = (c) => {
    const days = c.days_left;
    const state = days < 0 ? 'expired' : c.expiring ? 'expiring' : '';
    const validity = h('span', { class: `validity ${state}` },
      `${dateTime(c.not_before).slice(0, 10)} to ${dateTime(c.not_after).slice(0, 10)}`, h('br'),
      days < 0 ? `expired ${fromNow(c.not_after)}` : days === 0 ? 'expires today' : `expires in ${days} day${days === 1 ? '' : 's'}`);
    let action = null;
    if (c.place === 'opcua-rejected') {
      action = h('button', { type: 'button', class: 'primary', dataset: { trust: c.thumbprint } }, 'Trust…');
      action.addEventListener('click', () => act('Trust this client', c,
        () => post(`/api/v1/certificates/${c.thumbprint}/trust`),
        'Its next connection is accepted, within a second, without a restart. What it may do then is its user’s role, as for any client.'));
    } else if (c.place === 'opcua-trusted') {
      action = h('button', { type: 'button', class: 'danger', dataset: { remove: c.thumbprint } }, 'Remove…');
      action.addEventListener('click', () => act('Remove this client', c,
        () => del(`/api/v1/certificates/${c.thumbprint}`),
        'Its next connection is refused (a connection open now stays until it closes). It moves to the refused clients, where it can be trusted again.'));
    } else if (c.place === 'opcua-server') {
      action = h('button', { type: 'button', dataset: { action: 'renew' } }, 'Renew…');
      action.addEventListener('click', () => act('Renew the server’s certificate', c,
        () => post('/api/v1/certificates/opcua-server/renew'),
        'A new self-signed certificate is made (the old one kept beside it) and the OPC UA server alone restarts with it: its clients are disconnected, and each must trust the new certificate once, as the first. The other faces and the drives run on.'));
    }
    return h('tr', { class: state, dataset: { thumbprint: c.thumbprint, place: c.place } },
      h('td', {}, h('strong', {}, c.subject), c.self_signed ? h('small', {}, h('br'), 'self-signed') : h('small', {}, h('br'), `issued by ${c.issuer}`)),
      h('td', {}, c.application_uri ? h('code', {}, c.application_uri) : '–'),
      h('td', {}, validity),
      h('td', { class: 'thumb', title: `SHA-256 ${c.sha256}` }, pairs(c.thumbprint)),
      h('td', { class: 'file' }, c.file.split('/').slice(-3).join('/')),
      h('td', {}, action));
  };

  const refresh = async () => {
    let r;
    try {
      r = await get('/api/v1/certificates');
    } catch (e) {
      note.fail(e);
      return;
    }
    if (s.gone) return;
    notes.replaceChildren(...r.notes.map((n) => h('li', { class: 'warn' }, n)));
    const sections = [];
    for (const [place, title, about] of GROUPS) {
      const certs = r.certificates.filter((c) => c.place === place);
      const always = place === 'opcua-rejected' && r.certificates.some((c) => c.place.startsWith('opcua'));
      if (!certs.length && !always) continue;
      sections.push(h('section', { class: 'cert-group', dataset: { group: place } },
        h('h2', {}, title, ' ', h('span', { class: 'count' }, `(${certs.length})`)),
        h('p', { class: 'hint' }, about),
        certs.length ? h('div', { class: 'scroll' }, h('table', { class: 'log certs' },
          h('thead', {}, h('tr', {}, ['Subject', 'Application URI', 'Valid', 'Thumbprint (SHA-1)', 'File', ''].map((t) => h('th', { scope: 'col' }, t)))),
          h('tbody', {}, certs.map(row))))
          : h('p', {}, 'None.')));
    }
    if (!sections.length) sections.push(h('p', {}, 'This gateway serves no certificate: no [opcua], [http.tls] or [modbus_tcp.tls] is configured.'));
    body.replaceChildren(...sections);
  };

  refresh();
  return () => { s.gone = true; };
}
