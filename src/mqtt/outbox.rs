//! The outbox the edge node keeps what it cannot publish in: the trait
//! the node calls, and the outbox without a store. Below the node and the
//! store, which both name it.

use super::sparkplug_b::payload::Metric;

/// Where device data goes while it cannot be published (no broker, or the
/// primary host offline), and where it comes back from once the births
/// are out: the node replays it a little at a time, marked historical,
/// each message with the seq of when it is sent.
///
/// The node calls [`keep`](Outbox::keep) for each DDATA it could not send,
/// in order, and [`next`](Outbox::next) while connected and born, a few
/// times per tick, until it returns `None`.
pub trait Outbox: Send {
    /// Keeps the metrics of one DDATA of `device` (each with its own
    /// timestamp) for later.
    fn keep(&mut self, device: &str, metrics: Vec<Metric>);
    /// The oldest kept DDATA, taken out; `None` when nothing is kept.
    fn next(&mut self) -> Option<(String, Vec<Metric>)>;
}

/// The outbox without a store: what cannot be published is dropped (the
/// births republish every value when the link is back).
#[derive(Debug, Default)]
pub struct Discard;

impl Outbox for Discard {
    fn keep(&mut self, _device: &str, _metrics: Vec<Metric>) {}

    fn next(&mut self) -> Option<(String, Vec<Metric>)> {
        None
    }
}
