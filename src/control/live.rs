//! Only a live command moves a motor: one that its sender asked for now.
//! Not one a broker kept and hands to whoever subscribes (an MQTT retained
//! message, however old, from whoever once published it), not one the
//! broker queued for a session of an earlier connection while drivegate
//! was away, not one that waited in front of the bus longer than its
//! client waits for the answer (a Modbus TCP request behind a long queue,
//! which its client has given up on and may have sent again).
//!
//! A face only tells the core how a command reached it ([`Delivery`], and
//! for a write [`super::ControlRequest::received`]); the decisions are
//! here, pure, with the time passed in, and their words are the ones every
//! face answers with and the audit log keeps:
//!
//! - [`judge`]: a command delivered any way but live is refused, whatever
//!   it asks (a read, a brake, a setpoint): nothing of it is carried out;
//! - [`queue_wait`]: a write waits for the bus at most `[bus]
//!   queue_timeout_ms` from the moment its face received it (not from the
//!   moment the core took it), and one that waited that long already is
//!   not sent.

use std::time::{Duration, Instant};

use super::outcome::{Refusal, Rule};

/// How a command reached its face, as far as the face can tell.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Delivery {
    /// From its sender, now: a request on a connection, a message the
    /// broker forwarded as it was published.
    #[default]
    Live,
    /// MQTT: from the broker's retained messages (the retain flag set on
    /// delivery): stored by the broker, published at any time by anyone
    /// allowed to, delivered again at every subscription.
    Retained,
    /// MQTT: it came before the broker acknowledged this connection's
    /// subscription, so it was queued for a session of an earlier
    /// connection (the broker kept one, although drivegate asks for none).
    Queued,
    /// MQTT: its sender stamped it (`sent_ms`, Unix ms) before this
    /// connection began (`connected_ms`), on a connection where the broker
    /// kept a session: it was queued while drivegate was away.
    Older {
        /// When its sender says it sent it, Unix ms.
        sent_ms: u64,
        /// When this connection began, Unix ms.
        connected_ms: u64,
    },
}

impl Delivery {
    /// What became of such a command, as the audit log and the replies
    /// begin: "a retained command was ignored".
    pub fn ignored(self) -> &'static str {
        match self {
            Delivery::Live => "",
            Delivery::Retained => "a retained command was ignored",
            Delivery::Queued => "a command queued while drivegate was away was ignored",
            Delivery::Older { .. } => "a command older than drivegate's connection was ignored",
        }
    }

    /// Why, and what to do, after [`ignored`](Self::ignored).
    fn why(self) -> String {
        match self {
            Delivery::Live => String::new(),
            Delivery::Retained => "the broker delivered it from its retained messages, so it may have been published long ago, by anyone allowed to; nothing was sent. Publish commands without the retain flag (Sparkplug forbids retained commands) and clear the retained one on the broker (an empty retained message on its topic)".to_string(),
            Delivery::Queued => "it came before the broker confirmed this connection's subscription, so the broker kept it for an earlier session; nothing was sent. Send it again if it is still wanted".to_string(),
            Delivery::Older { sent_ms, connected_ms } => format!(
                "it was sent {} s before drivegate connected, and the broker kept it for an earlier session; nothing was sent. Send it again if it is still wanted",
                connected_ms.saturating_sub(sent_ms).div_ceil(1000)
            ),
        }
    }
}

/// Whether a command delivered as `delivery` may be carried out: refused,
/// with the words every face answers, unless it is [`Delivery::Live`].
pub fn judge(delivery: Delivery) -> Result<(), Refusal> {
    if delivery == Delivery::Live {
        return Ok(());
    }
    Err(Refusal {
        rule: Rule::NotLive,
        detail: format!("{}: {}", delivery.ignored(), delivery.why()),
    })
}

/// A write that waited in front of the bus as long as it may.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Late {
    /// How long it had waited since its face received it.
    pub waited: Duration,
}

/// How much longer a write received at `received` (`None`: just now) may
/// wait for the bus, at `now`, when the bus lets a job wait `queue_timeout`:
/// what is left of `queue_timeout` since it was received, or [`Late`].
pub fn queue_wait(
    received: Option<Instant>,
    now: Instant,
    queue_timeout: Duration,
) -> Result<Duration, Late> {
    let waited = received.map_or(Duration::ZERO, |r| now.saturating_duration_since(r));
    match queue_timeout.checked_sub(waited) {
        Some(left) if !left.is_zero() => Ok(left),
        _ => Err(Late { waited }),
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn only_a_live_command_passes() {
        assert_eq!(judge(Delivery::Live), Ok(()));
        for delivery in [
            Delivery::Retained,
            Delivery::Queued,
            Delivery::Older {
                sent_ms: 1_000,
                connected_ms: 61_500,
            },
        ] {
            let refusal = judge(delivery).unwrap_err();
            assert_eq!(refusal.rule, Rule::NotLive);
            assert!(
                refusal.detail.starts_with(delivery.ignored()),
                "{}",
                refusal.detail
            );
            assert!(
                refusal.detail.contains("nothing was sent"),
                "{}",
                refusal.detail
            );
        }
    }

    #[test]
    fn the_words_say_what_was_ignored_and_why() {
        let retained = judge(Delivery::Retained).unwrap_err().detail;
        assert!(
            retained.starts_with(
                "a retained command was ignored: the broker delivered it from its retained messages"
            ),
            "{retained}"
        );
        let older = judge(Delivery::Older {
            sent_ms: 1_000,
            connected_ms: 61_500,
        })
        .unwrap_err()
        .detail;
        assert!(
            older.contains("sent 61 s before drivegate connected"),
            "{older}"
        );
        assert_eq!(Rule::NotLive.name(), "not-live");
    }

    #[test]
    fn a_write_waits_for_the_bus_from_when_its_face_received_it() {
        let t0 = Instant::now();
        let qt = Duration::from_secs(5);
        // Received now, or not said: the whole queue timeout.
        assert_eq!(queue_wait(Some(t0), t0, qt), Ok(qt));
        assert_eq!(queue_wait(None, t0, qt), Ok(qt));
        // Waited 2 s behind its connection's earlier requests: 3 s left.
        let later = t0 + Duration::from_secs(2);
        assert_eq!(queue_wait(Some(t0), later, qt), Ok(Duration::from_secs(3)));
        // Waited the whole time already: not sent.
        let late = t0 + qt;
        assert_eq!(queue_wait(Some(t0), late, qt), Err(Late { waited: qt }));
        let later = t0 + Duration::from_secs(9);
        assert_eq!(
            queue_wait(Some(t0), later, qt),
            Err(Late {
                waited: Duration::from_secs(9)
            })
        );
    }
}
