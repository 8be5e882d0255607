//! How a command reached the node, told from what MQTT shows of it, for
//! both formats: the control core refuses every command that is not live
//! ([`crate::control::live`]); this says which ones are not, pure.
//!
//! The node's session starts clean (`clean_session`, MQTT 5 `clean_start`
//! with a session expiry of 0), so a broker keeps nothing for it while it
//! is away and delivers nothing of the past but retained messages. What
//! the node can tell of a message, in order:
//!
//! 1. the retain flag on delivery: the broker sends it from its retained
//!    messages (to a new subscription), whenever and by whomever it was
//!    published; a message published live with the flag reaches a node
//!    already subscribed without it, and is live;
//! 2. it came before the broker acknowledged the node's subscription
//!    (SUBACK): only a session the broker kept from an earlier connection
//!    could bring it, queued while the node was away;
//! 3. on a connection where the broker says it kept a session (CONNACK's
//!    session present, which a broker that honours the clean start never
//!    says), a Sparkplug payload stamped before the connection began was
//!    queued while the node was away.

use crate::control::live::Delivery;

/// What the node knows of its current connection.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub(super) struct Connected {
    /// When the broker accepted it, Unix ms.
    at_ms: u64,
    /// The broker said it kept a session from an earlier connection.
    session_present: bool,
    /// The broker acknowledged the node's subscriptions.
    subscribed: bool,
}

impl Connected {
    /// Accepted at `at_ms`, with or without a kept session; nothing
    /// subscribed yet.
    pub(super) fn accepted(at_ms: u64, session_present: bool) -> Self {
        Connected {
            at_ms,
            session_present,
            subscribed: false,
        }
    }

    /// The broker acknowledged the node's subscriptions (one SUBSCRIBE of
    /// every filter, so one SUBACK).
    pub(super) fn subscribed(&mut self) {
        self.subscribed = true;
    }

    /// How a message that came on this connection reached the node:
    /// `retained` its retain flag, `sent_ms` the time its sender stamped
    /// on it (Sparkplug's payload timestamp), if any.
    pub(super) fn delivery(&self, retained: bool, sent_ms: Option<u64>) -> Delivery {
        if retained {
            return Delivery::Retained;
        }
        if !self.subscribed {
            return Delivery::Queued;
        }
        match sent_ms {
            Some(sent_ms) if self.session_present && sent_ms < self.at_ms => Delivery::Older {
                sent_ms,
                connected_ms: self.at_ms,
            },
            _ => Delivery::Live,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const AT: u64 = 1_800_000_000_000;

    fn subscribed(session_present: bool) -> Connected {
        let mut c = Connected::accepted(AT, session_present);
        c.subscribed();
        c
    }

    #[test]
    fn a_retained_message_is_never_live() {
        for c in [
            Connected::accepted(AT, false),
            subscribed(false),
            subscribed(true),
        ] {
            assert_eq!(c.delivery(true, Some(AT + 5)), Delivery::Retained);
            assert_eq!(c.delivery(true, None), Delivery::Retained);
        }
    }

    #[test]
    fn a_message_before_the_subscription_was_acknowledged_was_queued_for_an_earlier_session() {
        let c = Connected::accepted(AT, true);
        assert_eq!(c.delivery(false, Some(AT + 5)), Delivery::Queued);
        assert_eq!(c.delivery(false, None), Delivery::Queued);
        // A clean session brings none, but one would be refused the same.
        let clean = Connected::accepted(AT, false);
        assert_eq!(clean.delivery(false, None), Delivery::Queued);
    }

    #[test]
    fn a_kept_session_refuses_what_was_sent_before_the_connection() {
        let kept = subscribed(true);
        assert_eq!(
            kept.delivery(false, Some(AT - 60_000)),
            Delivery::Older {
                sent_ms: AT - 60_000,
                connected_ms: AT
            }
        );
        assert_eq!(kept.delivery(false, Some(AT + 1)), Delivery::Live);
        // Without a stamp nothing more can be told.
        assert_eq!(kept.delivery(false, None), Delivery::Live);
        // A clean session keeps nothing: an old stamp is the sender's
        // clock, not a queued message.
        assert_eq!(
            subscribed(false).delivery(false, Some(AT - 60_000)),
            Delivery::Live
        );
    }
}
