//! The alarm book, pure: alarms raised, cleared and acknowledged, with the
//! time passed in (Unix milliseconds), and the changes each step makes
//! for the file and the stream. No I/O here.
//!
//! Two sorts of alarm:
//! - a *condition* (a fault, a stall, an offline drive, a drive that never
//!   answered, a bus down, a stop not confirmed) is active while it lasts: raising it again while it is
//!   active changes nothing; it clears when the condition ends;
//! - an *event* (a communication-loss stop, a refused safety write, a
//!   drive found moving at start when the safety journal was lost) is
//!   over when it happens: it is raised cleared, and the same event again
//!   while its alarm waits for an acknowledgement counts up on that alarm
//!   instead of adding one (a PLC retrying a refused write every 100 ms
//!   makes one alarm, not a thousand).
//!
//! Either waits for an operator's acknowledgement. The book keeps at most
//! `keep` alarms: past that, the oldest cleared-and-acknowledged go first,
//! then the oldest cleared ones, and only then (never in practice: a
//! condition is one per drive and kind) the oldest active one.

use std::collections::{BTreeMap, HashMap};

use serde::{Deserialize, Serialize};

use crate::listed::listed_enum;

listed_enum! {
    /// What an alarm is about.
    #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
    #[serde(rename_all = "kebab-case")]
    pub enum AlarmKind {
        /// The drive reports a fault (STATUS bits 2..0); `code` is its number.
        Fault,
        /// The motor stalled (STATUS bit 5).
        Stall,
        /// The drive stopped answering its polls.
        Offline,
        /// The drive has not answered once since its bus opened (a wrong
        /// baud rate or unit address, most often).
        NeverAnswered,
        /// A bus's serial port (or serial device server) failed.
        BusDown,
        /// A Modbus TCP client's communication-loss function ended its
        /// lease (silence, or its connection closed) and stopped the drive.
        CommLoss,
        /// The stop owed at the end of a lease was not confirmed by the
        /// drive (drivegate keeps trying).
        StopFailed,
        /// A write refused by a safety rule (a save or calibration while
        /// the motor turns, an address broadcast without confirmation).
        RefusedWrite,
        /// At start, the safety journal could not say who owned a drive
        /// found moving (it was unreadable, empty, only its header, or
        /// missing): `[safety] on_unknown_state` was applied to it.
        UnknownState,
        /// A certificate the daemon serves or trusts expires within 30
        /// days, or has expired (its `bus` is `certificate <thumbprint>`).
        CertificateExpiring,
    }
}

impl AlarmKind {
    /// Stable name for the API and the metrics.
    pub fn name(self) -> &'static str {
        match self {
            AlarmKind::Fault => "fault",
            AlarmKind::Stall => "stall",
            AlarmKind::Offline => "offline",
            AlarmKind::NeverAnswered => "never-answered",
            AlarmKind::BusDown => "bus-down",
            AlarmKind::CommLoss => "comm-loss",
            AlarmKind::StopFailed => "stop-failed",
            AlarmKind::RefusedWrite => "refused-write",
            AlarmKind::UnknownState => "unknown-state",
            AlarmKind::CertificateExpiring => "certificate-expiring",
        }
    }

    /// True for a condition (active while it lasts), false for an event.
    pub fn is_condition(self) -> bool {
        !matches!(
            self,
            AlarmKind::CommLoss | AlarmKind::RefusedWrite | AlarmKind::UnknownState
        )
    }
}

/// What makes two alarms the same: one active condition per key.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub struct AlarmKey {
    /// Its kind.
    pub kind: AlarmKind,
    /// The bus.
    pub bus: String,
    /// The drive, if it concerns one.
    pub drive: Option<String>,
    /// The fault code (0 for other kinds).
    pub code: u16,
}

/// An operator's acknowledgement.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Ack {
    /// Who (a token name, or a client address without tokens).
    pub by: String,
    /// When, Unix ms.
    pub at_ms: u64,
}

/// One alarm.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Alarm {
    /// Its number, unique for the state directory's life.
    pub id: u64,
    /// What it is about.
    pub kind: AlarmKind,
    /// The bus.
    pub bus: String,
    /// The drive, if it concerns one.
    pub drive: Option<String>,
    /// The fault code (0 for other kinds).
    pub code: u16,
    /// What happened, in words.
    pub text: String,
    /// What it means and what to check.
    pub help: String,
    /// Raised at, Unix ms.
    pub raised_ms: u64,
    /// Cleared at, Unix ms (`None`: active).
    pub cleared_ms: Option<u64>,
    /// The acknowledgement, if any.
    pub ack: Option<Ack>,
    /// Times it happened (an event repeated before it was acknowledged).
    pub count: u32,
    /// When it last happened, Unix ms.
    pub last_ms: u64,
}

impl Alarm {
    /// Its key.
    pub fn key(&self) -> AlarmKey {
        AlarmKey {
            kind: self.kind,
            bus: self.bus.clone(),
            drive: self.drive.clone(),
            code: self.code,
        }
    }

    /// True while its condition lasts.
    pub fn active(&self) -> bool {
        self.cleared_ms.is_none()
    }
}

/// An alarm to raise.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Raise {
    /// Its key.
    pub key: AlarmKey,
    /// What happened, in words.
    pub text: String,
    /// What it means and what to check.
    pub help: String,
}

/// A change the book made: for the file and the stream.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Change {
    /// A new alarm, or an event repeated on a waiting alarm (`count` up).
    Raised(Alarm),
    /// A condition ended.
    Cleared(Alarm),
    /// An operator acknowledged it.
    Acknowledged(Alarm),
    /// Dropped to keep the book within its bound.
    Dropped(u64),
}

/// Why an acknowledgement was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum AckError {
    /// No alarm has that number (any more).
    #[error(
        "no alarm {0}: it never was, or it was dropped to keep the alarm list within its bound"
    )]
    Unknown(u64),
}

/// The book.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct AlarmBook {
    alarms: BTreeMap<u64, Alarm>,
    /// The alarm of each active condition, and of each event waiting for
    /// its acknowledgement.
    open: HashMap<AlarmKey, u64>,
    next_id: u64,
    keep: usize,
}

impl AlarmBook {
    /// An empty book keeping at most `keep` alarms (at least 1).
    pub fn new(keep: usize) -> Self {
        AlarmBook {
            alarms: BTreeMap::new(),
            open: HashMap::new(),
            next_id: 1,
            keep: keep.max(1),
        }
    }

    /// A book holding `alarms` (read back from the file); numbering goes on
    /// after the highest. Over `keep`, the retention rule applies (the
    /// changes it makes are returned, for the file).
    pub fn restore(keep: usize, alarms: impl IntoIterator<Item = Alarm>) -> (Self, Vec<Change>) {
        let mut book = AlarmBook::new(keep);
        for a in alarms {
            book.next_id = book.next_id.max(a.id + 1);
            book.alarms.insert(a.id, a);
        }
        book.reindex();
        let mut changes = Vec::new();
        book.retain(&mut changes);
        (book, changes)
    }

    /// Numbers new alarms after `id` (the highest a file's records name,
    /// whether or not its alarm was kept): a number is never given twice.
    pub fn number_after(&mut self, id: u64) {
        self.next_id = self.next_id.max(id.saturating_add(1));
    }

    fn reindex(&mut self) {
        self.open = self
            .alarms
            .values()
            .filter(|a| Self::is_open(a))
            .map(|a| (a.key(), a.id))
            .collect();
    }

    /// Open: a condition still active, an event still unacknowledged.
    fn is_open(a: &Alarm) -> bool {
        if a.kind.is_condition() {
            a.active()
        } else {
            a.ack.is_none()
        }
    }

    /// Raises `raise` at `now_ms`: a new alarm, nothing (its condition is
    /// already active) or a repeat of a waiting event.
    pub fn raise(&mut self, raise: Raise, now_ms: u64) -> Vec<Change> {
        let mut changes = Vec::new();
        if let Some(alarm) = self
            .open
            .get(&raise.key)
            .and_then(|id| self.alarms.get_mut(id))
        {
            if raise.key.kind.is_condition() {
                return changes;
            }
            alarm.count = alarm.count.saturating_add(1);
            alarm.last_ms = now_ms;
            alarm.text = raise.text;
            changes.push(Change::Raised(alarm.clone()));
            return changes;
        }
        let id = self.next_id;
        self.next_id += 1;
        let condition = raise.key.kind.is_condition();
        let alarm = Alarm {
            id,
            kind: raise.key.kind,
            bus: raise.key.bus.clone(),
            drive: raise.key.drive.clone(),
            code: raise.key.code,
            text: raise.text,
            help: raise.help,
            raised_ms: now_ms,
            cleared_ms: (!condition).then_some(now_ms),
            ack: None,
            count: 1,
            last_ms: now_ms,
        };
        self.open.insert(raise.key, id);
        changes.push(Change::Raised(alarm.clone()));
        self.alarms.insert(id, alarm);
        self.retain(&mut changes);
        changes
    }

    /// Clears the active condition `key` at `now_ms`, if there is one.
    pub fn clear(&mut self, key: &AlarmKey, now_ms: u64) -> Vec<Change> {
        if !key.kind.is_condition() {
            return Vec::new();
        }
        let Some(id) = self.open.remove(key) else {
            return Vec::new();
        };
        let Some(alarm) = self.alarms.get_mut(&id) else {
            return Vec::new();
        };
        alarm.cleared_ms = Some(now_ms);
        vec![Change::Cleared(alarm.clone())]
    }

    /// Clears every active condition of `kind` on `bus` (and `drive`) but
    /// `keep_code`: a drive whose fault changed from one code to another.
    pub fn clear_other_codes(
        &mut self,
        kind: AlarmKind,
        bus: &str,
        drive: Option<&str>,
        keep_code: Option<u16>,
        now_ms: u64,
    ) -> Vec<Change> {
        let keys: Vec<AlarmKey> = self
            .open
            .keys()
            .filter(|k| {
                k.kind == kind
                    && k.bus == bus
                    && k.drive.as_deref() == drive
                    && Some(k.code) != keep_code
            })
            .cloned()
            .collect();
        keys.iter().flat_map(|k| self.clear(k, now_ms)).collect()
    }

    /// Clears every active condition `stale` says no one will ever clear
    /// (at start-up: a drive no longer configured, a stop the restart
    /// owns now).
    pub fn clear_where(&mut self, stale: impl Fn(&Alarm) -> bool, now_ms: u64) -> Vec<Change> {
        let keys: Vec<AlarmKey> = self
            .alarms
            .values()
            .filter(|a| a.kind.is_condition() && a.active() && stale(a))
            .map(Alarm::key)
            .collect();
        keys.iter().flat_map(|k| self.clear(k, now_ms)).collect()
    }

    /// Acknowledges alarm `id` for `by` at `now_ms`. An alarm already
    /// acknowledged keeps its first acknowledgement (and no change is
    /// made): `Ok(None)`.
    pub fn acknowledge(
        &mut self,
        id: u64,
        by: &str,
        now_ms: u64,
    ) -> Result<(Alarm, Option<Change>), AckError> {
        let alarm = self.alarms.get_mut(&id).ok_or(AckError::Unknown(id))?;
        if alarm.ack.is_some() {
            return Ok((alarm.clone(), None));
        }
        alarm.ack = Some(Ack {
            by: by.to_string(),
            at_ms: now_ms,
        });
        let alarm = alarm.clone();
        if !alarm.kind.is_condition() {
            self.open.remove(&alarm.key());
        }
        let mut changes = vec![Change::Acknowledged(alarm.clone())];
        self.retain(&mut changes);
        Ok((alarm, changes.into_iter().next()))
    }

    /// Drops alarms past `keep`: cleared and acknowledged first, then
    /// cleared, then any, oldest first within each.
    fn retain(&mut self, changes: &mut Vec<Change>) {
        while self.alarms.len() > self.keep {
            let pick =
                |f: &dyn Fn(&Alarm) -> bool| self.alarms.values().find(|a| f(a)).map(|a| a.id);
            let victim = pick(&|a| !a.active() && a.ack.is_some())
                .or_else(|| pick(&|a| !a.active()))
                .or_else(|| pick(&|_| true));
            let Some(id) = victim else { return };
            if let Some(a) = self.alarms.remove(&id)
                && self.open.get(&a.key()) == Some(&id)
            {
                self.open.remove(&a.key());
            }
            changes.push(Change::Dropped(id));
        }
    }

    /// Drive `old` of `bus` is named `new` now (a reload renamed it: the
    /// same motor): its alarms, open or not, are its under the new name;
    /// their words stay what was said at the time. The renamed alarms, for
    /// the file.
    pub fn rename(&mut self, bus: &str, old: &str, new: &str) -> Vec<Alarm> {
        let mut renamed = Vec::new();
        for a in self.alarms.values_mut() {
            if a.bus == bus && a.drive.as_deref() == Some(old) {
                a.drive = Some(new.to_string());
                renamed.push(a.clone());
            }
        }
        self.reindex();
        renamed
    }

    /// Every alarm, oldest first.
    pub fn alarms(&self) -> impl DoubleEndedIterator<Item = &Alarm> {
        self.alarms.values()
    }

    /// Alarm `id`.
    pub fn get(&self, id: u64) -> Option<&Alarm> {
        self.alarms.get(&id)
    }

    /// True when an alarm of `drive` on `bus` is open (a condition
    /// active, or an event waiting for its acknowledgement).
    pub fn has_open_for(&self, bus: &str, drive: &str) -> bool {
        self.open
            .keys()
            .any(|k| k.bus == bus && k.drive.as_deref() == Some(drive))
    }

    /// The most it keeps.
    pub fn keep(&self) -> usize {
        self.keep
    }

    /// How many it holds.
    pub fn len(&self) -> usize {
        self.alarms.len()
    }

    /// True when it holds none.
    pub fn is_empty(&self) -> bool {
        self.alarms.is_empty()
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn key(kind: AlarmKind, drive: &str, code: u16) -> AlarmKey {
        AlarmKey {
            kind,
            bus: "line1".into(),
            drive: Some(drive.into()),
            code,
        }
    }

    fn raise(kind: AlarmKind, drive: &str, code: u16) -> Raise {
        Raise {
            key: key(kind, drive, code),
            text: format!("{} on {drive}", kind.name()),
            help: "check it".into(),
        }
    }

    fn raised(changes: &[Change]) -> Alarm {
        match changes.first() {
            Some(Change::Raised(a)) => a.clone(),
            other => panic!("expected a raise, got {other:?}"),
        }
    }

    #[test]
    fn a_condition_is_raised_once_and_cleared_when_it_ends() {
        let mut book = AlarmBook::new(10);
        let a = raised(&book.raise(raise(AlarmKind::Offline, "conveyor", 0), 1000));
        assert_eq!(
            (a.id, a.raised_ms, a.cleared_ms, a.count),
            (1, 1000, None, 1)
        );
        // Still offline at the next poll: nothing new.
        assert!(
            book.raise(raise(AlarmKind::Offline, "conveyor", 0), 2000)
                .is_empty()
        );
        let cleared = book.clear(&key(AlarmKind::Offline, "conveyor", 0), 3000);
        assert!(matches!(&cleared[..], [Change::Cleared(a)] if a.cleared_ms == Some(3000)));
        // Cleared twice is nothing.
        assert!(
            book.clear(&key(AlarmKind::Offline, "conveyor", 0), 3500)
                .is_empty()
        );
        // Offline again: a new alarm.
        let again = raised(&book.raise(raise(AlarmKind::Offline, "conveyor", 0), 4000));
        assert_eq!(again.id, 2);
        assert_eq!(book.len(), 2);
    }

    #[test]
    fn an_event_is_raised_cleared_and_counts_its_repeats_until_acknowledged() {
        let mut book = AlarmBook::new(10);
        let a = raised(&book.raise(raise(AlarmKind::RefusedWrite, "lift", 0), 100));
        assert_eq!(a.cleared_ms, Some(100));
        let again = raised(&book.raise(raise(AlarmKind::RefusedWrite, "lift", 0), 250));
        assert_eq!((again.id, again.count, again.last_ms), (a.id, 2, 250));
        let (acked, change) = book.acknowledge(a.id, "panel", 300).unwrap();
        assert_eq!(acked.ack.as_ref().map(|k| k.by.as_str()), Some("panel"));
        assert!(matches!(change, Some(Change::Acknowledged(_))));
        // After the acknowledgement the same event is a new alarm.
        let b = raised(&book.raise(raise(AlarmKind::RefusedWrite, "lift", 0), 400));
        assert_ne!(b.id, a.id);
        assert_eq!(b.count, 1);
    }

    #[test]
    fn an_acknowledgement_is_kept_first_come_and_unknown_ids_are_refused() {
        let mut book = AlarmBook::new(10);
        let a = raised(&book.raise(raise(AlarmKind::Stall, "lift", 0), 100));
        let (first, change) = book.acknowledge(a.id, "alice", 200).unwrap();
        assert!(change.is_some());
        let (second, change) = book.acknowledge(a.id, "bob", 300).unwrap();
        assert_eq!(change, None);
        assert_eq!(first, second);
        assert_eq!(second.ack.unwrap().by, "alice");
        // Acknowledged but still active: the condition still holds.
        assert!(book.get(a.id).unwrap().active());
        assert_eq!(book.acknowledge(99, "x", 1), Err(AckError::Unknown(99)));
    }

    #[test]
    fn a_fault_that_changes_code_clears_the_old_one() {
        let mut book = AlarmBook::new(10);
        raised(&book.raise(raise(AlarmKind::Fault, "lift", 4), 100));
        let changes = book.clear_other_codes(AlarmKind::Fault, "line1", Some("lift"), Some(5), 200);
        assert_eq!(changes.len(), 1);
        let five = raised(&book.raise(raise(AlarmKind::Fault, "lift", 5), 200));
        assert_eq!(five.code, 5);
        // Another drive's fault is not touched.
        raised(&book.raise(raise(AlarmKind::Fault, "conveyor", 4), 250));
        let cleared = book.clear_other_codes(AlarmKind::Fault, "line1", Some("lift"), None, 300);
        assert!(matches!(&cleared[..], [Change::Cleared(a)] if a.code == 5));
        assert_eq!(book.alarms().filter(|a| a.active()).count(), 1);
    }

    #[test]
    fn the_bound_drops_cleared_and_acknowledged_first_then_cleared_then_oldest() {
        let mut book = AlarmBook::new(3);
        let a = raised(&book.raise(raise(AlarmKind::Offline, "a", 0), 1));
        let b = raised(&book.raise(raise(AlarmKind::Offline, "b", 0), 2));
        let c = raised(&book.raise(raise(AlarmKind::Offline, "c", 0), 3));
        book.clear(&key(AlarmKind::Offline, "a", 0), 4);
        book.clear(&key(AlarmKind::Offline, "b", 0), 5);
        book.acknowledge(b.id, "op", 6).unwrap();
        // b is cleared and acknowledged: it goes first, though a is older.
        let changes = book.raise(raise(AlarmKind::Offline, "d", 0), 7);
        assert_eq!(changes.last(), Some(&Change::Dropped(b.id)));
        // Then a (cleared, not acknowledged).
        let changes = book.raise(raise(AlarmKind::Offline, "e", 0), 8);
        assert_eq!(changes.last(), Some(&Change::Dropped(a.id)));
        // All active: the oldest goes, and its condition with it.
        let changes = book.raise(raise(AlarmKind::Offline, "f", 0), 9);
        assert_eq!(changes.last(), Some(&Change::Dropped(c.id)));
        assert_eq!(book.len(), 3);
        assert!(book.clear(&key(AlarmKind::Offline, "c", 0), 10).is_empty());
    }

    #[test]
    fn conditions_nobody_will_clear_are_cleared_on_request() {
        let mut book = AlarmBook::new(10);
        raised(&book.raise(raise(AlarmKind::Offline, "gone", 0), 1));
        raised(&book.raise(raise(AlarmKind::Offline, "kept", 0), 2));
        raised(&book.raise(raise(AlarmKind::RefusedWrite, "gone", 0), 3));
        let changes = book.clear_where(|a| a.drive.as_deref() == Some("gone"), 4);
        // Only the active condition: the event was never active.
        assert!(
            matches!(&changes[..], [Change::Cleared(a)] if a.drive.as_deref() == Some("gone") && a.kind == AlarmKind::Offline)
        );
        assert_eq!(book.alarms().filter(|a| a.active()).count(), 1);
    }

    #[test]
    fn a_restored_book_goes_on_numbering_and_keeps_its_open_alarms() {
        let mut book = AlarmBook::new(10);
        raised(&book.raise(raise(AlarmKind::Offline, "a", 0), 1));
        let ev = raised(&book.raise(raise(AlarmKind::CommLoss, "a", 0), 2));
        let saved: Vec<Alarm> = book.alarms().cloned().collect();
        let (mut restored, changes) = AlarmBook::restore(10, saved);
        assert!(changes.is_empty());
        assert_eq!(restored, book);
        // The active condition is still the same alarm; the waiting event
        // still counts up.
        assert!(
            restored
                .raise(raise(AlarmKind::Offline, "a", 0), 3)
                .is_empty()
        );
        let again = raised(&restored.raise(raise(AlarmKind::CommLoss, "a", 0), 4));
        assert_eq!((again.id, again.count), (ev.id, 2));
        let next = raised(&restored.raise(raise(AlarmKind::Stall, "a", 0), 5));
        assert_eq!(next.id, 3);
        // Restored over its bound, it drops as it would have.
        let (small, changes) = AlarmBook::restore(1, restored.alarms().cloned());
        assert_eq!(small.len(), 1);
        assert_eq!(changes.len(), 2);
    }

    #[test]
    fn a_renamed_drive_keeps_its_alarms_under_its_new_name() {
        let mut book = AlarmBook::new(10);
        book.raise(raise(AlarmKind::Offline, "conveyor", 0), 1);
        book.raise(raise(AlarmKind::Offline, "lift", 0), 1);
        let renamed = book.rename("line1", "conveyor", "belt");
        assert_eq!(renamed.len(), 1);
        assert_eq!(renamed[0].drive.as_deref(), Some("belt"));
        assert!(book.has_open_for("line1", "belt"));
        assert!(!book.has_open_for("line1", "conveyor"));
        // Its condition ends under the new name.
        assert_eq!(book.clear(&key(AlarmKind::Offline, "belt", 0), 2).len(), 1);
        assert!(book.has_open_for("line1", "lift"));
    }
}
