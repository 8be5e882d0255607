// Configuration (admin): the file drivegate runs from, with its comments,
// in an editor that checks as you type (the daemon's own check-config,
// POST /api/v1/config/check: each problem at its line and column), the
// lines changed against the file, what applying would change in the
// plant's terms, and Apply: the file written whole (the previous versions
// kept), reloaded, and the reload's answer in words. The change is made
// on the version read (If-Match): another admin's change meanwhile is
// refused and named. Where drivegate may not write its file, Apply offers
// the new file to download.

import { ApiError, post, request } from '../api.js';
import { h, Note, confirmDialog } from '../ui.js';
import { tabs, reloadAnswer, saveText, when } from '../gateway.js';

export const page = {
  id: 'config',
  title: 'Configuration',
  role: 'admin',
  nav: { path: '/config', label: 'Gateway', key: 'g', tip: 'This gateway: its configuration, certificates and API tokens' },
  match: (path) => (path === '/config' ? {} : null),
  mount,
};

/** Quiet time after a keystroke before the text is checked, ms. */
const CHECK_AFTER_MS = 300;

function mount(main) {
  const s = { base: null, sha256: null, file: null, writable: true, seq: 0, checked: null, timer: 0, gone: false };
  const textarea = h('textarea', {
    class: 'config-text', spellcheck: 'false', wrap: 'off', autocomplete: 'off', rows: 28,
    'aria-label': 'The configuration file', dataset: { field: 'config-text' },
  });
  const gutter = h('div', { class: 'gutter', 'aria-hidden': 'true' });
  const status = h('p', { class: 'check', role: 'status', dataset: { check: 'status' } });
  const remarks = h('ul', { class: 'remarks', dataset: { check: 'remarks' } });
  const changes = h('ul', { class: 'changes', dataset: { field: 'changes' } });
  const diff = h('div', { class: 'diff-view', dataset: { field: 'diff' } });
  const banner = h('div', { class: 'file-banner', role: 'note' });
  const about = h('p', { class: 'hint', dataset: { field: 'about' } });
  const kept = h('p', { class: 'hint small', dataset: { field: 'generations' } });
  const apply = h('button', { type: 'button', class: 'primary', disabled: true, dataset: { action: 'apply' } }, 'Apply…');
  const revert = h('button', { type: 'button', disabled: true, dataset: { action: 'revert' } }, 'Undo my edits');
  const reread = h('button', { type: 'button', dataset: { action: 'reread' } }, 'Read the file again');
  const download = h('button', { type: 'button', hidden: true, dataset: { action: 'download' } }, 'Download the new file');
  const note = new Note();
  const result = h('div', { class: 'apply-result', 'aria-live': 'polite' });
  main.append(h('section', { class: 'panel config-page' },
    tabs('config'),
    h('h1', {}, 'Configuration'),
    about, banner,
    h('div', { class: 'editor' }, gutter, textarea),
    status, remarks,
    h('div', { class: 'row' }, apply, download, revert, reread),
    note.el, result,
    h('div', { class: 'config-below' },
      h('section', {}, h('h2', {}, 'Changed lines'), diff),
      h('section', {}, h('h2', {}, 'What Apply does'), changes)),
    kept));

  const lineHeight = () => parseFloat(getComputedStyle(textarea).lineHeight) || 20;
  const drawGutter = () => {
    const lines = textarea.value.split('\n').length;
    const marks = new Map();
    for (const r of (s.checked ? s.checked.warnings : [])) if (r.line) marks.set(r.line, 'warn');
    for (const r of (s.checked ? s.checked.problems : [])) if (r.line) marks.set(r.line, 'bad');
    const rows = [];
    for (let i = 1; i <= lines; i++) {
      const mark = marks.get(i);
      rows.push(h('div', { class: mark || null, dataset: { line: String(i) } }, mark === 'bad' ? `✖ ${i}` : mark === 'warn' ? `! ${i}` : String(i)));
    }
    gutter.replaceChildren(...rows);
    gutter.scrollTop = textarea.scrollTop;
  };
  textarea.addEventListener('scroll', () => { gutter.scrollTop = textarea.scrollTop; });

  /** Puts the caret at line:column and shows that line. */
  const goTo = (line, column) => {
    const lines = textarea.value.split('\n');
    let offset = 0;
    for (let i = 0; i < Math.min(line - 1, lines.length); i++) offset += lines[i].length + 1;
    offset += Math.max(0, (column || 1) - 1);
    textarea.focus();
    textarea.setSelectionRange(offset, offset);
    textarea.scrollTop = Math.max(0, (line - 4) * lineHeight());
  };

  const remark = (r, kind) => {
    const where = r.line ? `line ${r.line}${r.column ? `, column ${r.column}` : ''}` : 'the file';
    const item = h('li', { class: kind, dataset: { line: String(r.line), column: String(r.column) } },
      h('strong', {}, kind === 'bad' ? 'Error' : 'Warning'), ` at ${where}: `, r.message);
    if (r.line) {
      const go = h('button', { type: 'button', class: 'link-button' }, 'Go to it');
      go.addEventListener('click', () => goTo(r.line, r.column));
      item.append(' ', go);
    }
    return item;
  };

  const drawDiff = (hunks) => {
    if (!hunks.length) { diff.replaceChildren(h('p', { class: 'hint' }, 'None: the text is the file’s.')); return; }
    diff.replaceChildren(...hunks.map((hk) => h('pre', { class: 'hunk' },
      h('span', { class: 'hunk-head' }, `lines ${hk.new_start}–${hk.new_start + Math.max(hk.new_lines, 1) - 1}`),
      ...hk.lines.map((l) => h('span', { class: `dl ${l.op}` }, `${l.op === 'added' ? '+' : l.op === 'removed' ? '−' : ' '} ${l.text}`)))));
  };

  const edited = () => s.base !== null && textarea.value !== s.base;

  const drawState = () => {
    const c = s.checked;
    const valid = c && c.valid;
    const changed = edited();
    revert.disabled = !changed;
    apply.disabled = !valid || (!changed && s.running) || !s.writable;
    download.hidden = s.writable;
    download.disabled = !valid || !changed;
    if (!c) { status.textContent = 'checking…'; status.className = 'check'; return; }
    const n = c.problems.length;
    status.className = `check ${n ? 'bad' : 'good'}`;
    status.textContent = n
      ? `${n === 1 ? 'One problem' : `${n} problems`}: drivegate would refuse this file (nothing is written while it does not pass).`
      : `Valid, as drivegate check-config says${c.warnings.length ? `, with ${c.warnings.length} warning${c.warnings.length === 1 ? '' : 's'}` : ''}.${changed ? '' : ' No edits yet.'}`;
    remarks.replaceChildren(...c.problems.map((r) => remark(r, 'bad')), ...c.warnings.map((r) => remark(r, 'warn')));
    drawDiff(c.diff || []);
    const plant = c.valid ? (c.changes || []).filter((t) => t !== 'no change') : [];
    changes.replaceChildren(...(plant.length ? plant.map((t) => h('li', {}, t))
      : [h('li', { class: 'hint' }, c.valid ? 'Nothing changes in the running plant.' : 'Nothing: the text does not pass the check.')]));
    drawGutter();
  };

  const check = async () => {
    const seq = ++s.seq;
    try {
      const r = await post('/api/v1/config/check', { text: textarea.value });
      if (seq !== s.seq || s.gone) return;
      s.checked = r;
    } catch (e) {
      if (seq !== s.seq || s.gone) return;
      note.fail(e);
      return;
    }
    drawState();
  };
  textarea.addEventListener('input', () => {
    drawGutter();
    result.replaceChildren();
    note.clear();
    clearTimeout(s.timer);
    status.textContent = 'checking…';
    status.className = 'check';
    s.timer = setTimeout(check, CHECK_AFTER_MS);
  });
  // Tab types two spaces (TOML's indentation), Shift+Tab leaves the field.
  textarea.addEventListener('keydown', (e) => {
    if (e.key === 'Tab' && !e.shiftKey && !e.ctrlKey && !e.altKey) {
      e.preventDefault();
      document.execCommand('insertText', false, '  ');
    }
  });

  /**
   * Reads the file; `keepText` keeps what is typed (after a refusal),
   * `quiet` keeps the note of the last action.
   */
  const load = async (keepText, quiet = false) => {
    if (!quiet) note.pending('reading the configuration file…');
    let r;
    try {
      r = await request('GET', '/api/v1/config/file');
    } catch (e) {
      note.fail(e);
      return;
    }
    if (s.gone) return;
    const f = r.json;
    s.base = f.text; s.sha256 = r.etag || f.sha256; s.file = f.file; s.writable = f.writable; s.running = f.running;
    if (!keepText) textarea.value = f.text;
    about.replaceChildren('The file drivegate runs from: ', h('code', {}, f.file),
      '. Edit it here: it is checked as you type, as ', h('code', {}, 'drivegate check-config'),
      ' checks it. Apply writes it whole (the previous version kept beside it) and reloads it without a restart: drives that do not change keep running.');
    const notes = [];
    if (!f.writable) {
      notes.push(h('p', { class: 'note warn', dataset: { banner: 'read-only' } }, f.not_writable,
        ' Apply is replaced by “Download the new file”.'));
    }
    if (!f.running) {
      notes.push(h('p', { class: 'note warn', dataset: { banner: 'not-running' } },
        'The file on disk is not what runs: it was changed since the last reload, or the reload refused it. Applying it reloads it.'));
    }
    banner.replaceChildren(...notes);
    const gens = f.generations || [];
    kept.textContent = `${gens.length ? `Previous versions kept beside it: ${gens.map((g) => g.path.split('/').pop()).join(', ')} (newest first).` : 'No previous version kept yet.'}`
      + `${f.last_change ? ` Last change through drivegate: ${f.last_change.what}, by ${f.last_change.by} at ${when(f.last_change.at)}.` : ''}`;
    if (!quiet) note.clear();
    s.checked = null;
    drawState();
    await check();
  };

  revert.addEventListener('click', () => {
    textarea.value = s.base;
    result.replaceChildren();
    check();
  });
  reread.addEventListener('click', () => load(edited()));
  download.addEventListener('click', () => {
    const name = (s.file || 'drivegate.toml').split('/').pop();
    saveText(name, textarea.value);
    note.ok(`saved as ${name}: put it in place of ${s.file} by hand (sudoedit ${s.file}) and reload (systemctl reload drivegate)`);
  });

  apply.addEventListener('click', async () => {
    const c = s.checked;
    const plant = ((c && c.changes) || []).filter((t) => t !== 'no change');
    const answer = await confirmDialog({
      title: 'Apply this configuration?',
      body: [
        `${s.file} is written whole (the version it replaces is kept beside it) and reloaded at once.`,
        plant.length ? h('ul', { class: 'changes' }, plant.map((t) => h('li', {}, t))) : 'Nothing changes in the running plant.',
        'Drives that are not named keep running. A drive removed or moved that turns is stopped first.',
      ],
      confirm: 'Apply',
    });
    if (!answer.ok) return;
    apply.disabled = true;
    note.pending('writing the file and reloading…');
    result.replaceChildren();
    try {
      const r = await request('PUT', '/api/v1/config/file', { body: { text: textarea.value }, headers: { 'If-Match': `"${s.sha256}"` } });
      const reply = r.json;
      s.base = textarea.value;
      s.sha256 = r.etag || reply.sha256;
      s.running = true;
      note.ok(`written and reloaded (${reply.diff.length} place${reply.diff.length === 1 ? '' : 's'} changed)`);
      result.replaceChildren(reloadAnswer(reply.reload));
      await load(false, true);
    } catch (e) {
      note.fail(e);
      const type = e instanceof ApiError && e.problem && e.problem.type ? e.problem.type : '';
      if (type.endsWith(':config-edited')) {
        result.replaceChildren(h('p', { class: 'hint' },
          'Your text is kept. “Read the file again” compares it with the file as it is now; make your change on that and apply again.'));
      } else if (type.endsWith(':config-read-only')) {
        s.writable = false;
        result.replaceChildren(h('p', { class: 'hint' }, 'Your text is kept: “Download the new file” saves it.'));
      }
      drawState();
    }
  });

  load(false);
  return () => { s.gone = true; clearTimeout(s.timer); };
}
