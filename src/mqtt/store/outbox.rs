//! The store as the edge node's [`Outbox`]: a DDATA kept is its metrics
//! (each with its own timestamp) as a Sparkplug payload under the device's
//! name; what comes back out is paced by [`Pacer`].
//!
//! Messages leave the store on disk a batch at a time, once the node has
//! taken the whole batch: a crash in the middle of a batch sends that
//! batch again after the restart (at least once), and a cursor written
//! per message would cost a rename each.

use std::collections::VecDeque;
use std::path::Path;
use std::sync::Arc;
use std::time::{Instant, SystemTime};

use prost::Message;

use super::pacing::{Pacer, Pacing};
use super::{DIR, Store, StoreError, StoredMessage};
use crate::metrics::Metrics;
use crate::mqtt::outbox::Outbox;
use crate::mqtt::sparkplug_b::Payload;
use crate::mqtt::sparkplug_b::payload::Metric;

/// How many messages leave the disk at once.
const BATCH: usize = 64;

/// The node's outbox on disk.
pub struct StoredOutbox {
    store: Store,
    pacer: Pacer,
    metrics: Arc<Metrics>,
    /// Read from the store, not all handed out yet.
    batch: VecDeque<StoredMessage>,
    /// How many the batch held: they leave the store once it is empty.
    batch_len: usize,
    /// The store's drop count when the batch was read: a drop since means
    /// the batch's messages may be gone from the disk already.
    batch_dropped: u64,
    /// The last error was logged (one warning per run of errors).
    warned: bool,
}

impl StoredOutbox {
    /// Opens the store in `state_dir`'s `mqtt-store`, bounded to
    /// `max_mb` MB, with what an earlier run left in it.
    pub fn open(state_dir: &Path, max_mb: u64, metrics: Arc<Metrics>) -> Result<Self, StoreError> {
        let store = Store::open(&state_dir.join(DIR), max_mb.saturating_mul(1024 * 1024))?;
        let waiting = store.figures().messages;
        if waiting > 0 {
            tracing::info!(
                "MQTT store: {waiting} messages kept from before the restart are replayed once the births are out"
            );
        }
        let outbox = StoredOutbox {
            store,
            pacer: Pacer::new(Pacing::default()),
            metrics,
            batch: VecDeque::new(),
            batch_len: 0,
            batch_dropped: 0,
            warned: false,
        };
        outbox.report();
        outbox
            .metrics
            .mqtt()
            .store_skipped(outbox.store.figures().skipped_bytes);
        Ok(outbox)
    }

    fn report(&self) {
        let f = self.store.figures();
        self.metrics.mqtt().store(f.bytes, f.messages, f.dropped);
    }

    fn failed(&mut self, e: &StoreError) {
        if !self.warned {
            tracing::warn!("{e}; data that cannot be published now is lost");
            self.warned = true;
        }
    }

    /// The next message on disk, a batch read when needed.
    fn take(&mut self) -> Option<StoredMessage> {
        if self.store.figures().dropped != self.batch_dropped {
            // The bound dropped the oldest while this batch was out: what
            // is left of it may not be on disk any more.
            self.batch.clear();
            self.batch_len = 0;
        }
        if self.batch.is_empty() {
            if self.batch_len > 0 {
                let sent = std::mem::take(&mut self.batch_len);
                if let Err(e) = self.store.pop(sent) {
                    self.failed(&e);
                }
            }
            match self.store.peek(BATCH) {
                Ok(batch) => {
                    self.batch_len = batch.len();
                    self.batch = batch.into();
                    self.batch_dropped = self.store.figures().dropped;
                }
                Err(e) => {
                    self.failed(&e);
                    return None;
                }
            }
        }
        self.batch.pop_front()
    }
}

impl Outbox for StoredOutbox {
    fn keep(&mut self, device: &str, metrics: Vec<Metric>) {
        let payload = Payload {
            metrics,
            ..Default::default()
        };
        let message = StoredMessage {
            topic: device.to_string(),
            payload: payload.encode_to_vec(),
            at_ms: crate::control::journal::format::unix_ms(SystemTime::now()),
        };
        match self.store.push(&message) {
            Ok(()) => self.warned = false,
            Err(e) => self.failed(&e),
        }
        self.report();
    }

    fn next(&mut self) -> Option<(String, Vec<Metric>)> {
        if self.pacer.allowance(Instant::now(), 0) == 0 {
            return None;
        }
        let out = loop {
            let m = self.take()?;
            match Payload::decode(m.payload.as_slice()) {
                Ok(p) => break (m.topic, p.metrics),
                // Framed and CRC-checked, so only a payload of another
                // version could fail here: skipped.
                Err(e) => {
                    tracing::warn!("MQTT store: a kept message of {} is skipped: {e}", m.topic)
                }
            }
        };
        self.pacer.spent(1);
        if self.batch.is_empty() && self.batch_len > 0 {
            let sent = std::mem::take(&mut self.batch_len);
            if let Err(e) = self.store.pop(sent) {
                self.failed(&e);
            }
        }
        self.report();
        Some(out)
    }
}

/// The outbox `config` asks for: the store in `[safety] state_dir` when
/// there is an `[mqtt]` section, a state directory and `store_max_mb > 0`;
/// else [`Discard`](crate::mqtt::Discard), saying why in the log.
pub fn for_config(config: &crate::config::Config, metrics: &Arc<Metrics>) -> Box<dyn Outbox> {
    let Some(mqtt) = config.mqtt.as_ref() else {
        return Box::new(crate::mqtt::Discard);
    };
    if mqtt.store_max_mb == 0 {
        tracing::info!(
            "MQTT store: off ([mqtt] store_max_mb = 0): data that cannot be published is dropped"
        );
        return Box::new(crate::mqtt::Discard);
    }
    let Some(dir) = config.safety.state_dir() else {
        tracing::warn!(
            "MQTT store: none ([safety] state_dir unset and no $STATE_DIRECTORY): data that cannot be published is dropped"
        );
        return Box::new(crate::mqtt::Discard);
    };
    match StoredOutbox::open(&dir, mqtt.store_max_mb, metrics.clone()) {
        Ok(outbox) => Box::new(outbox),
        Err(e) => {
            tracing::warn!("{e}; data that cannot be published is dropped");
            Box::new(crate::mqtt::Discard)
        }
    }
}
