// A speed typed into a field and kept, beside the hold-to-jog: the lease
// the user chooses decides what stops the motor.
//
// - "While this page is open": the setpoint goes over the stream with the
//   jog's short lease ([safety] jog_lease_ms), and the page renews it for
//   as long as it is open and shown. A closed or crashed tab closes the
//   socket (the lease ends at once); a hidden tab, a frozen page or a cut
//   network stop the renewals, and drivegate stops the motor when the
//   lease runs out. As with the jog, the page never sends a stop of its
//   own: what the user sees is what happens when the page dies.
// - "For N seconds": the setpoint goes over REST with a lease of N s that
//   nobody renews: drivegate stops the motor N s later, whether the page
//   is still open or not.
//
// "Stop" stops renewing, sends a zero speed (confirmed by the drive) and
// then gives the lease back.

import { drivePath, put, api, ApiError } from './api.js';

/** Renewals per lease: one lost or late renewal does not stop the motor. */
const RENEWALS_PER_LEASE = 3;

export class SpeedSetpoint {
  /**
   * `stream` carries the held setpoint and its renewals; `report`
   * receives {state, rpm, until, why, error, result} to show; `leaseMs`
   * is the held setpoint's lease.
   */
  constructor(stream, drive, report, leaseMs) {
    this.stream = stream;
    this.drive = drive;
    this.report = report;
    this.leaseMs = leaseMs;
    this.timer = null;
    this.generation = 0;
    this.held = false;
    this.onHidden = () => {
      if (document.visibilityState === 'hidden') this.release('the tab was hidden');
    };
    document.addEventListener('visibilitychange', this.onHidden);
  }

  /** Sends `rpm`, held while this page is open. Resolves with the reply. */
  async hold(rpm) {
    this.stopRenewing();
    const generation = ++this.generation;
    this.report({ state: 'sending', rpm });
    try {
      const result = await this.stream.command('setpoint', this.drive, { speed_rpm: rpm, lease_ms: this.leaseMs });
      if (generation !== this.generation) return result;
      this.held = true;
      this.timer = setInterval(() => this.renew(generation), this.leaseMs / RENEWALS_PER_LEASE);
      this.report({ state: 'held', rpm, result });
      return result;
    } catch (e) {
      if (generation === this.generation) this.report({ state: 'idle', error: e });
      throw e;
    }
  }

  /** Sends `rpm` with a lease of `seconds` that nobody renews. */
  async timed(rpm, seconds) {
    this.stopRenewing();
    const generation = ++this.generation;
    this.report({ state: 'sending', rpm });
    try {
      const result = await put(drivePath(this.drive, '/setpoint'), { speed_rpm: rpm, lease_ms: Math.round(seconds * 1000) });
      if (generation !== this.generation) return result;
      const until = Date.now() + (result.lease ? result.lease.expires_in_ms : seconds * 1000);
      this.report({ state: 'timed', rpm, until, result });
      return result;
    } catch (e) {
      if (generation === this.generation) this.report({ state: 'idle', error: e });
      throw e;
    }
  }

  renew(generation) {
    this.stream.command('lease-renew', this.drive, { lease_ms: this.leaseMs }).catch((e) => {
      if (generation !== this.generation) return;
      // The lease is gone (brake, deactivation, another client's
      // setpoint, the connection): stop asking, and say why.
      this.stopRenewing();
      this.report({ state: 'idle', error: e });
    });
  }

  /** Stops renewing a held setpoint: drivegate stops the motor when its lease runs out. */
  release(why) {
    if (!this.held) return;
    this.stopRenewing();
    this.generation += 1;
    this.report({ state: 'released', why });
  }

  /**
   * Zero speed, confirmed by the drive, then the lease given back (the
   * motor is stopped already, so its end needs no stop of its own).
   */
  async stop() {
    this.stopRenewing();
    const generation = ++this.generation;
    this.report({ state: 'stopping' });
    try {
      const result = await put(drivePath(this.drive, '/setpoint'), { speed_rpm: 0 });
      await api('DELETE', drivePath(this.drive, '/lease')).catch((e) => {
        // No lease left (it ran out, or a brake ended it) is what Stop wants.
        if (!(e instanceof ApiError && e.status === 409)) throw e;
      });
      if (generation === this.generation) this.report({ state: 'stopped', result });
      return result;
    } catch (e) {
      if (generation === this.generation) this.report({ state: 'idle', error: e });
      throw e;
    }
  }

  /** The lease ended (news from the stream): nothing is held any more. */
  ended() {
    if (!this.held) return;
    this.stopRenewing();
    this.generation += 1;
  }

  stopRenewing() {
    if (this.timer !== null) clearInterval(this.timer);
    this.timer = null;
    this.held = false;
  }

  /** The page is left: stop renewing (the lease runs out) and unhook. */
  dispose() {
    this.release('the page was left');
    document.removeEventListener('visibilitychange', this.onHidden);
  }
}
