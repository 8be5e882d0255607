//! New timing for a master on its open port: a reload applied in place.

use super::{Bounds, Gaps, Interframe, Limits, MasterSettings, RtuMaster, SERIAL_ADAPTER_LATENCY};
use crate::bus::reply_timeout::ReplyTimeout;
use crate::bus::transport::Transport;

impl RtuMaster {
    /// Takes `settings` between two transactions, on the same port. The
    /// line's baud rate and RS-485 direction control are the open port's:
    /// they stay (a change of them reopens the port). What was learned
    /// under the old timing and still holds is kept: each drive's reply
    /// timeout (bounded by the new floor and ceiling when it is used),
    /// unless the guard changed, and each drive's silence, unless
    /// `interframe` changed.
    pub fn retune(&mut self, settings: MasterSettings) {
        let old = self.settings;
        let settings = MasterSettings {
            line: old.line,
            rs485: old.rs485,
            ..settings
        };
        if settings == old {
            return;
        }
        let margin = self.bounds.margin;
        self.bounds = Bounds::for_line(
            old.line.t3_5(),
            settings.response_timeout,
            settings.reply_timeout_floor,
        );
        self.bounds.margin = margin;
        if settings.guard != old.guard {
            *self.timeouts = [ReplyTimeout::default(); 256];
        }
        if settings.interframe != old.interframe {
            let mut interframe = settings.interframe;
            // As at the start: no silence is learned through a network.
            if matches!(self.port, Transport::Tcp { .. }) && interframe == Interframe::Auto {
                interframe = Interframe::Spec;
            }
            self.gaps = Gaps::new(
                interframe,
                Limits::for_line(old.line, SERIAL_ADAPTER_LATENCY),
            );
        }
        self.settings = settings;
    }
}
