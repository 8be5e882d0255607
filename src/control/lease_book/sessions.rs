//! Sessions: a WebSocket or a Modbus TCP connection whose closing ends its
//! leases, and the communication-loss function (a lease per setpoint,
//! renewed by any request of the session, ended by its silence).

use std::time::{Duration, Instant};

use super::types::SESSION_CLOSED;
use super::{CommLoss, Effect, Holder, LeaseBook, Session, StopReason, Terms};
use crate::control::caller::{Face, SessionId};
use crate::control::stop_action::StopAction;

impl LeaseBook {
    /// A session opened; `closing` is how its end reads in messages
    /// ("its WebSocket closed"), `comm_loss` its communication-loss
    /// function, if it has one.
    pub fn session_opened(
        &mut self,
        session: SessionId,
        closing: &'static str,
        comm_loss: Option<CommLoss>,
    ) {
        self.sessions
            .insert(session, Session { closing, comm_loss });
    }

    /// A session closed: its leases end now, with their stop.
    pub fn session_closed(&mut self, session: SessionId, now: Instant) -> Vec<Effect> {
        let closing = self
            .sessions
            .remove(&session)
            .map_or(SESSION_CLOSED, |s| s.closing);
        let drives: Vec<(usize, Option<Face>)> = self
            .slots
            .iter()
            .filter_map(|(d, s)| {
                let lease = s.lease.as_ref()?;
                (lease.holder == Holder::Session(session)).then_some((
                    *d,
                    lease
                        .comm_loss
                        .then_some(lease.face.unwrap_or(Face::ModbusTcp)),
                ))
            })
            .collect();
        let mut effects = Vec::new();
        for (drive, comm_loss) in drives {
            if let Some(face) = comm_loss
                && !self.shut_down
            {
                effects.push(Effect::CommLoss {
                    drive,
                    closed: true,
                    face,
                });
            }
            self.end_with_stop(drive, StopReason::SessionClosed(closing), now);
        }
        effects.extend(self.tick(now));
        effects
    }

    /// Any request came on `session`: its communication-loss leases run
    /// for their length from `now` (never brought closer while a setpoint
    /// waits for the bus). Other leases are renewed only when asked.
    pub fn session_active(&mut self, session: SessionId, now: Instant) {
        for slot in self.slots.values_mut() {
            if let Some(lease) = slot.lease.as_mut()
                && lease.comm_loss
                && lease.holder == Holder::Session(session)
            {
                lease.deadline = if lease.confirmed {
                    now + lease.length
                } else {
                    (now + lease.length).max(lease.deadline)
                };
            }
        }
    }

    /// The lease a setpoint or mode command of a caller in `session` takes:
    /// the one it asked for (`asked`, with `action`), else, in a session
    /// with a communication-loss time, a communication-loss lease; else
    /// none.
    pub fn terms(
        &self,
        session: Option<SessionId>,
        asked: Option<Duration>,
        action: Option<StopAction>,
    ) -> Option<Terms> {
        if let Some(length) = asked {
            return Some(Terms {
                length,
                action,
                comm_loss: false,
            });
        }
        let comm_loss = self.sessions.get(&session?)?.comm_loss?;
        Some(Terms {
            length: comm_loss.after,
            action: Some(comm_loss.action),
            comm_loss: true,
        })
    }
}
