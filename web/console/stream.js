// The WebSocket stream (/api/v1/stream): live statuses and events for every
// drive, and commands whose replies come back by id. Reconnects by itself
// with a growing delay; while it is down the page says so and marks every
// value stale.
//
// A setpoint sent here with a lease ends, and stops the motor, when this
// socket closes: that is what makes hold-to-jog safe when the tab closes
// or the network is cut (see jog.js).

import { ApiError, streamProtocols } from './api.js';

export class Stream {
  constructor() {
    this.ws = null;
    this.state = 'connecting';
    this.handlers = new Map();
    this.pending = new Map();
    this.nextId = 1;
    this.delay = 500;
    this.timer = null;
    this.stopped = false;
    // For the benchmark and the tests: messages received by type.
    this.counts = {};
  }

  /** Calls `fn(message)` for every message of `type` ('*' for all, 'state' for connection changes). */
  on(type, fn) {
    if (!this.handlers.has(type)) this.handlers.set(type, new Set());
    this.handlers.get(type).add(fn);
    return () => this.handlers.get(type).delete(fn);
  }

  emit(type, message) {
    for (const fn of this.handlers.get(type) || []) {
      try { fn(message); } catch (e) { console.error(e); }
    }
  }

  connect() {
    this.stopped = false;
    clearTimeout(this.timer);
    const scheme = location.protocol === 'https:' ? 'wss' : 'ws';
    const ws = new WebSocket(`${scheme}://${location.host}/api/v1/stream?drives=all`, streamProtocols());
    this.ws = ws;
    this.setState('connecting');
    ws.onopen = () => {
      this.delay = 500;
      this.setState('open');
    };
    ws.onmessage = (event) => {
      let m;
      try { m = JSON.parse(event.data); } catch { return; }
      this.counts[m.type] = (this.counts[m.type] || 0) + 1;
      if (m.type === 'reply') {
        const p = this.pending.get(m.id);
        if (p) {
          this.pending.delete(m.id);
          if (m.ok) p.resolve(m.result);
          else p.reject(new ApiError(m.problem || { detail: 'refused' }, m.problem && m.problem.status));
        }
        return;
      }
      this.emit(m.type, m);
      this.emit('*', m);
    };
    ws.onclose = (event) => {
      if (this.ws !== ws) return;
      this.ws = null;
      this.failPending();
      this.setState('closed', event.code === 1001 ? 'drivegate is stopping' : '');
      if (!this.stopped) {
        this.timer = setTimeout(() => this.connect(), this.delay);
        this.delay = Math.min(this.delay * 2, 5000);
      }
    };
  }

  /** Closes the socket (its leases end, so jogged motors stop). */
  close() {
    this.stopped = true;
    clearTimeout(this.timer);
    if (this.ws) this.ws.close(1000, 'closed by the page');
  }

  setState(state, reason = '') {
    this.state = state;
    this.emit('state', { state, reason });
  }

  failPending() {
    for (const p of this.pending.values()) {
      p.reject(new ApiError({
        title: 'Connection lost',
        detail: 'the connection to drivegate closed before the answer: a command still queued for the bus was dropped, one already sent may have been carried out',
      }, 0));
    }
    this.pending.clear();
  }

  /** Sends a command; resolves with the REST body, rejects with ApiError. */
  command(op, target, body) {
    if (!this.ws || this.ws.readyState !== WebSocket.OPEN) {
      return Promise.reject(new ApiError({
        title: 'Not connected',
        detail: 'the live connection to drivegate is down, so nothing was sent; it reconnects by itself',
      }, 0));
    }
    const id = this.nextId++;
    const message = { type: 'command', id, op, body: body ?? null };
    if (op === 'scan' || op === 'set-address') message.bus = target;
    else message.drive = target;
    return new Promise((resolve, reject) => {
      this.pending.set(id, { resolve, reject });
      this.ws.send(JSON.stringify(message));
    });
  }
}
