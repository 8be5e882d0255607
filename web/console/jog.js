// Hold-to-jog: while a button (or key) is held, a setpoint with a short
// lease is sent over the stream and the lease renewed; on release the page
// simply stops renewing.
//
// The motor is stopped by the daemon, never by the page's goodwill: the
// lease ends `leaseMs` after the last renewal (a released button, a window
// that lost focus, a frozen or closed tab, a cut network) and drivegate
// then stops the motor ([safety] on_lease_expiry). A lease taken over the
// stream also ends as soon as the socket closes. The page sends no "stop"
// of its own on release, so what a user sees on release is exactly what
// happens when the page dies.

/** The lease of a jog when the daemon names none ([safety] jog_lease_ms), ms. */
export const DEFAULT_LEASE_MS = 300;
/** Renewals per lease: one lost or late renewal does not stop the motor. */
const RENEWALS_PER_LEASE = 3;

export class Jog {
  /**
   * `stream` carries the commands; `setpoint(direction)` gives the body
   * ({speed_rpm} or {torque_a}) for a direction of +1 or -1; `report`
   * receives {state, error} for the page to show; `leaseMs` is how long the
   * motor runs on after the last renewal.
   */
  constructor(stream, drive, setpoint, report, leaseMs = DEFAULT_LEASE_MS) {
    this.leaseMs = leaseMs;
    this.stream = stream;
    this.drive = drive;
    this.setpoint = setpoint;
    this.report = report;
    this.direction = 0;
    this.timer = null;
    this.generation = 0;
    this.onBlur = () => this.release('the window lost focus');
    this.onHidden = () => { if (document.visibilityState === 'hidden') this.release('the tab was hidden'); };
    window.addEventListener('blur', this.onBlur);
    document.addEventListener('visibilitychange', this.onHidden);
  }

  /** Starts jogging in `direction` (+1 or -1); ignored while already held. */
  press(direction) {
    if (this.direction !== 0) return;
    let body;
    try {
      body = this.setpoint(direction);
    } catch (e) {
      this.report({ state: 'idle', error: e });
      return;
    }
    this.direction = direction;
    const generation = ++this.generation;
    this.report({ state: 'starting', direction });
    this.stream.command('setpoint', this.drive, { ...body, lease_ms: this.leaseMs })
      .then(() => {
        if (generation !== this.generation || this.direction === 0) return;
        this.report({ state: 'running', direction });
        this.timer = setInterval(() => this.renew(generation), this.leaseMs / RENEWALS_PER_LEASE);
      })
      .catch((e) => {
        if (generation !== this.generation) return;
        this.direction = 0;
        this.report({ state: 'idle', error: e });
      });
  }

  renew(generation) {
    this.stream.command('lease-renew', this.drive, { lease_ms: this.leaseMs }).catch((e) => {
      if (generation !== this.generation) return;
      // The lease is gone (brake, deactivation, another client, the
      // connection): stop asking, and say why.
      this.stopTimer();
      this.direction = 0;
      this.report({ state: 'idle', error: e });
    });
  }

  /** Stops renewing: the daemon stops the motor when the lease runs out. */
  release(why = 'released') {
    if (this.direction === 0) return;
    this.direction = 0;
    this.generation += 1;
    this.stopTimer();
    this.report({ state: 'released', why });
  }

  stopTimer() {
    if (this.timer !== null) clearInterval(this.timer);
    this.timer = null;
  }

  /** Ends the jog and removes the window listeners (the page is left). */
  dispose() {
    this.release('the page was left');
    window.removeEventListener('blur', this.onBlur);
    document.removeEventListener('visibilitychange', this.onHidden);
  }

  /**
   * Makes `button` a hold-to-jog control in `direction`: pointer held, or
   * Space/Enter held while it has focus. Leaving it, losing the pointer or
   * the focus releases.
   */
  bind(button, direction) {
    const down = (e) => {
      if (e.button !== undefined && e.button !== 0) return;
      e.preventDefault();
      button.setPointerCapture?.(e.pointerId);
      this.press(direction);
    };
    const up = () => this.release();
    button.addEventListener('pointerdown', down);
    button.addEventListener('pointerup', up);
    button.addEventListener('pointercancel', up);
    button.addEventListener('lostpointercapture', up);
    button.addEventListener('contextmenu', (e) => e.preventDefault());
    button.addEventListener('keydown', (e) => {
      if ((e.key === ' ' || e.key === 'Enter') && !e.repeat) {
        e.preventDefault();
        this.press(direction);
      } else if (e.key === ' ' || e.key === 'Enter') {
        e.preventDefault();
      }
    });
    button.addEventListener('keyup', (e) => {
      if (e.key === ' ' || e.key === 'Enter') {
        e.preventDefault();
        this.release();
      }
    });
    button.addEventListener('blur', () => this.release('the control lost focus'));
  }
}
