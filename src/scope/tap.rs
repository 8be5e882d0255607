//! The scope's side of the bus: the wire tap shows it every frame (it
//! keeps the status replies of a running capture as samples and notes the
//! writes that may trigger it), and it steers the polling while it
//! captures. With no capture running each call reads one atomic flag.

use std::time::Instant;

use super::Scope;
use crate::bus::Origin;
use crate::bus::observers::{PollSteering, Received, Sent, Steer, WireObserver};
use crate::modbus::function::EXCEPTION_BIT;

impl WireObserver for Scope {
    fn sent(&self, sent: &Sent<'_>) {
        if sent.attempt == 1 && sent.frame.get(1).is_some_and(|&f| is_write(f)) {
            self.on_write(sent.unit, sent.origin, sent.at);
        }
    }

    fn received(&self, got: &Received<'_>) {
        let exception = got.frame.get(1).is_some_and(|f| f & EXCEPTION_BIT != 0);
        if got.fault.is_none() && !exception {
            self.on_reply(got.unit, got.request, got.frame, got.request_end);
        }
    }

    fn stray(&self, _unit: u8, _bytes: &[u8], _at: Instant) {}
}

impl PollSteering for Scope {
    fn steer(
        &self,
        now: Instant,
        plan_due: &dyn Fn(u8) -> bool,
        offline: &dyn Fn(u8) -> bool,
    ) -> Option<Steer> {
        Scope::steer(self, now, plan_due, offline)
    }

    fn polled(&self, unit: u8, now: Instant) {
        Scope::polled(self, unit, now);
    }

    fn poll_origin(&self, unit: u8) -> Origin {
        Scope::poll_origin(self, unit)
    }
}

/// Function codes that change a device: the scope's write trigger.
pub fn is_write(function: u8) -> bool {
    matches!(function, 0x05 | 0x06 | 0x0F | 0x10 | 0x15 | 0x16 | 0x17)
}
