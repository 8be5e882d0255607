// Settings of one drive (admin): over-current protection, both ramps (the
// ramp time by the manual's formulas (2) and (3) shown as the user types),
// load inertia, RS-485 control. Every form starts from the values read from
// the drive; every save to flash goes through a confirmation that says
// what it does.

import { drivePath, get, put } from '../api.js';
import { h, fmt, Note, run, numberField, confirmDialog, clock } from '../ui.js';
import { speedRampTime, speedRampAlpha, positionRampTime, positionRampAlpha } from '../ramps.js';

export const page = {
  id: 'settings',
  title: 'Settings',
  role: 'admin',
  nav: { path: '/settings', label: 'Settings', key: 's' },
  match: (path) => {
    if (path === '/settings') return { name: null };
    const m = /^\/settings\/([^/]+)$/.exec(path);
    return m ? { name: decodeURIComponent(m[1]) } : null;
  },
  mount,
};

function mount(main, { name }, { store, navigate }) {
  const chosen = name || store.order[0];
  const picker = h('select', { id: 'settings-drive', 'aria-label': 'Drive' },
    store.order.map((n) => h('option', { value: n, selected: n === chosen }, n)));
  picker.addEventListener('change', () => navigate(`/settings/${encodeURIComponent(picker.value)}`));
  const readNote = new Note();
  const forms = h('div', { class: 'forms' });
  main.append(h('section', { class: 'panel' },
    h('h1', {}, 'Settings of ', picker),
    h('p', { class: 'hint' }, 'Values are read from the drive. "Write" changes them until the drive is powered off; "Save to flash…" also keeps them over power loss.'),
    readNote.el, forms));
  if (!chosen) return null;
  const d = store.drives.get(chosen);
  run(null, readNote, 'reading the drive…', () => get(drivePath(chosen, '/settings')), (r) => {
    forms.replaceChildren(
      protectionForm(chosen, r),
      speedRampForm(chosen, r, d ? d.gearRatio : r.gear_ratio),
      positionRampForm(chosen, r),
      inertiaForm(chosen, r),
      rs485Form(chosen, r));
    return `read from the drive at ${clock(r.read_at)}`;
  });
  return null;
}

/** Write and save buttons for a form whose body `body()` builds. */
function actions(name, path, what, body, note, done) {
  const write = h('button', { type: 'button', class: 'primary', dataset: { action: 'write' } }, 'Write');
  const save = h('button', { type: 'button', dataset: { action: 'save' } }, 'Save to flash…');
  const send = (b, extra) => run(b, note, 'writing…', () => {
    const payload = body();
    if (payload instanceof Error) return Promise.reject(payload);
    return put(drivePath(name, path), { ...payload, ...extra });
  }, (r) => `${r.saved ? 'written and saved to flash' : 'written'}: ${r.written.filter((w) => !w.quantity.startsWith('save')).map((w) => `${w.quantity} ${w.value}${w.unit ? ` ${w.unit}` : ''}`).join(', ')} — confirmed by the drive${done ? done(r) : ''}`);
  write.addEventListener('click', () => send(write, { save: false }));
  save.addEventListener('click', async () => {
    const answer = await confirmDialog({
      title: `Save ${what} of ${name} to flash?`,
      body: [
        `The drive writes these values to its flash memory and keeps them after a power cycle, replacing the saved ones.`,
        'The manual allows this only while the motor stands still: drivegate reads the drive first and refuses while it turns.',
      ],
      check: 'Save even while the motor turns (force; logged)',
      confirm: 'Save to flash',
    });
    if (answer.ok) send(save, { save: true, force: answer.checked });
  });
  return h('div', { class: 'row' }, write, save);
}

function form(title, ...children) {
  return h('form', { class: 'group', onsubmit: (e) => e.preventDefault() }, h('h2', {}, title), ...children);
}

const invalid = (text) => new Error(text);

/** A ramp time with four significant digits (a fast ramp is milliseconds). */
const seconds4 = (t) => String(Number(t.toPrecision(4)));

function protectionForm(name, r) {
  const limit = numberField('Over-current limit (A, 0 to 15.99)', { value: fmt(r.protection.limit_a, 2), dataset: { field: 'limit_a' } });
  const stall = numberField('Stall time (ms, 0 to 60000)', { value: String(r.protection.stall_ms), dataset: { field: 'stall_ms' } });
  const note = new Note();
  return form('Over-current protection',
    h('p', { class: 'hint' }, 'Above the limit for longer than the stall time, the drive stalls the motor until a fault reset.'),
    h('div', { class: 'row' }, limit.wrap, stall.wrap),
    actions(name, '/protection', 'the protection', () => {
      if (!Number.isFinite(limit.value()) || !Number.isFinite(stall.value())) return invalid('type a current limit in A and a stall time in ms');
      return { limit_a: limit.value(), stall_ms: stall.value() };
    }, note),
    note.el);
}

/** A ramp form: by time (with the step it is for) or by alpha, with the time shown live. */
function rampForm({ name, title, path, alpha, stepLabel, stepDefault, stepKey, time, solve }) {
  const byTime = h('input', { type: 'radio', name: `${path}-by`, value: 'time', checked: true });
  const byAlpha = h('input', { type: 'radio', name: `${path}-by`, value: 'alpha' });
  const seconds = numberField('Ramp time (s)', { dataset: { field: `${stepKey}-time` } });
  const step = numberField(stepLabel, { value: String(stepDefault), dataset: { field: stepKey } });
  const alphaField = numberField('Alpha (0 = ramp off)', { value: String(alpha), dataset: { field: `${stepKey}-alpha` } });
  const preview = h('p', { class: 'preview', role: 'status', dataset: { preview: stepKey } });
  const currentTime = time(alpha, stepDefault);
  seconds.input.value = currentTime ? seconds4(currentTime) : '';
  const update = () => {
    const st = step.value();
    if (byTime.checked) {
      const t = seconds.value();
      const a = Number.isFinite(t) && Number.isFinite(st) ? solve(t, st) : null;
      preview.textContent = a ? `alpha ${a}: ${seconds4(time(a, st))} s for a step of ${st} (formula ${stepKey === 'step_rpm' ? 2 : 3})` : 'type a time and a step';
    } else {
      const a = alphaField.value();
      const t = Number.isFinite(a) && Number.isFinite(st) ? time(a, st) : null;
      preview.textContent = a === 0 ? 'ramp off: setpoints apply at once' : t ? `${seconds4(t)} s for a step of ${st} (formula ${stepKey === 'step_rpm' ? 2 : 3})` : 'type alpha and a step';
    }
    seconds.wrap.hidden = !byTime.checked;
    alphaField.wrap.hidden = byTime.checked;
  };
  for (const el of [byTime, byAlpha, seconds.input, step.input, alphaField.input]) el.addEventListener('input', update);
  update();
  const note = new Note();
  return form(title,
    h('fieldset', { class: 'row' }, h('legend', {}, 'Set by'),
      h('label', {}, byTime, ' ramp time'), h('label', {}, byAlpha, ' alpha')),
    h('div', { class: 'row' }, seconds.wrap, alphaField.wrap, step.wrap),
    preview,
    actions(name, path, `the ${title.toLowerCase()}`, () => {
      if (byTime.checked) {
        if (!Number.isFinite(seconds.value()) || !Number.isFinite(step.value())) return invalid('type a ramp time in s and the step it is for');
        return { time_s: seconds.value(), [stepKey]: step.value() };
      }
      if (!Number.isFinite(alphaField.value())) return invalid('type alpha (a whole number, 0 turns the ramp off)');
      return { alpha: alphaField.value() };
    }, note, (r) => (r.time_s ? ` (alpha ${r.alpha}: ${fmt(r.time_s, 3)} s for the step)` : ` (alpha ${r.alpha})`)),
    note.el);
}

function speedRampForm(name, r, gearRatio) {
  return rampForm({
    name, title: 'Speed ramp', path: '/ramps/speed', alpha: r.speed_ramp.alpha,
    stepLabel: 'Step (rpm at the output)', stepDefault: 1000, stepKey: 'step_rpm',
    time: (a, rpm) => speedRampTime(a, rpm, gearRatio),
    solve: (t, rpm) => speedRampAlpha(t, rpm, gearRatio),
  });
}

function positionRampForm(name, r) {
  return rampForm({
    name, title: 'Position ramp', path: '/ramps/position', alpha: r.position_ramp.alpha,
    stepLabel: 'Step (°)', stepDefault: 180, stepKey: 'step_deg',
    time: (a, deg) => positionRampTime(a, deg),
    solve: (t, deg) => positionRampAlpha(t, deg),
  });
}

function inertiaForm(name, r) {
  const ratio = numberField('Load inertia (× rotor, 1 to 65535)', { value: String(r.inertia_ratio), dataset: { field: 'inertia' } });
  const note = new Note();
  return form('Load inertia',
    h('div', { class: 'row' }, ratio.wrap),
    actions(name, '/inertia', 'the load inertia', () => (Number.isFinite(ratio.value()) ? { ratio: ratio.value() } : invalid('type the inertia ratio')), note),
    note.el);
}

function rs485Form(name, r) {
  const note = new Note();
  const state = h('p', {}, r.rs485_control ? 'RS-485 (this gateway) controls the motor.' : 'CAN controls the motor: setpoints from this gateway are echoed but ignored.');
  const toggle = h('button', { type: 'button', dataset: { action: 'rs485' } }, r.rs485_control ? 'Hand control to CAN…' : 'Take control over RS-485');
  let enabled = r.rs485_control;
  toggle.addEventListener('click', async () => {
    if (enabled) {
      const a = await confirmDialog({
        title: `Hand ${name} to CAN?`,
        body: ['The drive will ignore the setpoints of this gateway (and of SCADA through it) and take them from CAN. Jog, go-to and torque here will stop moving it.'],
        confirm: 'Hand to CAN', danger: true,
      });
      if (!a.ok) return;
    }
    const r2 = await run(toggle, note, 'writing…', () => put(drivePath(name, '/rs485-control'), { enabled: !enabled }),
      () => `${!enabled ? 'RS-485' : 'CAN'} controls the motor now — confirmed by the drive`);
    if (r2) {
      enabled = !enabled;
      state.textContent = enabled ? 'RS-485 (this gateway) controls the motor.' : 'CAN controls the motor: setpoints from this gateway are echoed but ignored.';
      toggle.textContent = enabled ? 'Hand control to CAN…' : 'Take control over RS-485';
    }
  });
  return form('RS-485 control', state, h('div', { class: 'row' }, toggle), note.el);
}
