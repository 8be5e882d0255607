//! The alarm book's alarms (`crate::control::alarms`) as OPC UA
//! `AlarmConditionType` events: each raise, clear and acknowledgement the
//! core announces is an event of its drive (or bus) and of the Server
//! object, with a new EventId; the condition's id (`Alarms/<number>`) is
//! the alarm's number, which the acknowledgement names
//! (`super::conditions`).
//!
//! async-opcua has the event types but no condition instances: [`Event`]
//! answers what alarm clients select that the generated types cannot (the
//! ConditionId, with an empty browse path; a two-state variable's own
//! text, `ActiveState` = "Active").

use std::collections::HashMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use opcua::core_namespace::events::{AlarmConditionType, TwoStateVariableType};
use opcua::nodes::{BaseEventType, Event, NamespaceMap};
use opcua::server::SubscriptionCache;
use opcua::types::event_field::EventField;
use opcua::types::{
    AttributeId, ByteString, DateTime, LocalizedText, NodeId, NumericRange, ObjectTypeId,
    QualifiedName, Variant,
};
use tokio::sync::broadcast::error::RecvError;
use tokio_util::sync::CancellationToken;

use super::address::Nodes;
use super::spec;
use super::values::date_time;
use crate::control::alarms::{Alarm, AlarmKind, AlarmNews};
use crate::control::{Control, ControlEvent};
use crate::metrics::Metrics;

/// One state of one alarm, as an event.
#[derive(Debug)]
pub struct AlarmEvent {
    inner: AlarmConditionType,
    condition: NodeId,
    source: NodeId,
}

impl EventField for AlarmEvent {
    fn get_value(
        &self,
        attribute_id: AttributeId,
        index_range: &NumericRange,
        remaining_path: &[QualifiedName],
    ) -> Variant {
        self.inner
            .get_value(attribute_id, index_range, remaining_path)
    }
}

impl Event for AlarmEvent {
    fn get_field(
        &self,
        type_definition_id: &NodeId,
        attribute_id: AttributeId,
        index_range: &NumericRange,
        browse_path: &[QualifiedName],
    ) -> Variant {
        // The ConditionId: the NodeId of the condition, no browse path.
        if browse_path.is_empty() && attribute_id == AttributeId::NodeId {
            return self.condition.clone().into();
        }
        // A null type definition (a where clause's operand) is
        // BaseEventType; the generated types answer it with nothing.
        let base: NodeId = ObjectTypeId::BaseEventType.into();
        let type_definition_id = if type_definition_id.is_null() {
            &base
        } else {
            type_definition_id
        };
        // A two-state variable's own value (its text); the generated types
        // answer only its properties (Id, ...).
        if let [field] = browse_path
            && attribute_id == AttributeId::Value
            && field.namespace_index == 0
        {
            let two = match field.name.as_ref() {
                "ActiveState" => Some(&self.inner.active_state),
                "AckedState" => Some(&self.inner.base.acked_state),
                "ConfirmedState" => Some(&self.inner.base.confirmed_state),
                "EnabledState" => Some(&self.inner.base.base.enabled_state),
                _ => None,
            };
            if let Some(two) = two {
                return two.base.value.clone().into();
            }
        }
        self.inner
            .get_field(type_definition_id, attribute_id, index_range, browse_path)
    }

    fn time(&self) -> &DateTime {
        self.inner.time()
    }

    fn event_type_id(&self) -> &NodeId {
        self.inner.event_type_id()
    }
}

impl AlarmEvent {
    /// The node the event is of (a drive, or a bus).
    pub fn source(&self) -> &NodeId {
        &self.source
    }
}

fn two_state(id: bool, yes: &str, no: &str) -> TwoStateVariableType {
    let mut s = TwoStateVariableType {
        id,
        true_state: LocalizedText::new("en", yes),
        false_state: LocalizedText::new("en", no),
        ..Default::default()
    };
    s.base.value = LocalizedText::new("en", if id { yes } else { no });
    s
}

/// How severe an alarm of `kind` is (1 to 1000).
pub fn severity(kind: AlarmKind) -> u16 {
    match kind {
        AlarmKind::BusDown | AlarmKind::StopFailed | AlarmKind::UnknownState => 900,
        AlarmKind::Fault => 800,
        AlarmKind::Stall | AlarmKind::CommLoss => 700,
        AlarmKind::Offline | AlarmKind::NeverAnswered => 600,
        AlarmKind::RefusedWrite | AlarmKind::CertificateExpiring => 400,
    }
}

fn at_ms(ms: u64) -> SystemTime {
    UNIX_EPOCH + Duration::from_millis(ms)
}

/// The events of the alarms, and each alarm's latest EventId (an
/// acknowledgement must name it).
pub struct AlarmEvents {
    nodes: Nodes,
    latest: Mutex<HashMap<u64, Vec<u8>>>,
}

impl AlarmEvents {
    /// The events of namespace `nodes`.
    pub fn new(nodes: Nodes) -> Self {
        AlarmEvents {
            nodes,
            latest: Mutex::new(HashMap::new()),
        }
    }

    /// The condition (alarm) a node id names.
    pub fn alarm_of(&self, id: &NodeId) -> Option<u64> {
        if id.namespace != self.nodes.ns {
            return None;
        }
        spec::alarm_of(spec::path_of(id)?)
    }

    /// True when `event_id` is alarm `alarm`'s latest event.
    pub fn is_latest(&self, alarm: u64, event_id: &[u8]) -> bool {
        self.latest
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(&alarm)
            .is_some_and(|e| e.as_slice() == event_id)
    }

    /// The event of `alarm`'s state now, with a new EventId.
    pub fn event(&self, alarm: &Alarm) -> AlarmEvent {
        let event_id = {
            let mut id = alarm.id.to_be_bytes().to_vec();
            let nanos = SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos());
            id.extend_from_slice(&nanos.to_be_bytes());
            id
        };
        {
            let mut latest = self.latest.lock().unwrap_or_else(|p| p.into_inner());
            if latest.len() > 100_000 {
                latest.clear();
            }
            latest.insert(alarm.id, event_id.clone());
        }
        let (source, source_name) = match &alarm.drive {
            Some(drive) => (self.nodes.id(&spec::drive_path(drive)), drive.clone()),
            None => (
                self.nodes.id(&spec::bus_path(&alarm.bus)),
                alarm.bus.clone(),
            ),
        };
        let mut ev = AlarmConditionType::new_event_now(
            AlarmConditionType::event_type_id(),
            ByteString::from(event_id),
            LocalizedText::new("en", alarm.text.as_str()),
            &NamespaceMap::new(),
        );
        {
            let base: &mut BaseEventType = &mut ev.base.base.base;
            base.source_node = source.clone();
            base.source_name = source_name.as_str().into();
            base.severity = severity(alarm.kind);
            base.receive_time = DateTime::now();
            base.time = date_time(at_ms(alarm.last_ms.max(alarm.raised_ms)));
        }
        let acked = alarm.ack.is_some();
        let condition = &mut ev.base.base;
        condition.condition_name = alarm.kind.name().into();
        condition.retain = alarm.active() || !acked;
        condition.enabled_state = two_state(true, "Enabled", "Disabled");
        condition.condition_class_id = ObjectTypeId::BaseConditionClassType.into();
        ev.base.acked_state = two_state(acked, "Acknowledged", "Unacknowledged");
        ev.base.confirmed_state = two_state(true, "Confirmed", "Unconfirmed");
        ev.active_state = two_state(alarm.active(), "Active", "Inactive");
        AlarmEvent {
            inner: ev,
            condition: self.nodes.id(&spec::alarm_path(alarm.id)),
            source,
        }
    }

    /// Sends `alarm`'s state to the subscribers of its source (the crate
    /// hands every event to the Server object's subscribers too).
    pub fn publish(&self, subscriptions: &SubscriptionCache, alarm: &Alarm) {
        let ev = self.event(alarm);
        let source = ev.source().clone();
        subscriptions.notify_events([(&ev as &dyn Event, &source)].into_iter());
    }
}

/// Publishes every alarm the core raises, clears or acknowledges, until
/// `stop`.
pub async fn run(
    events: Arc<AlarmEvents>,
    control: Control,
    subscriptions: Arc<SubscriptionCache>,
    metrics: Arc<Metrics>,
    stop: CancellationToken,
) {
    let mut rx = control.subscribe();
    loop {
        let published = tokio::select! {
            r = rx.recv() => r,
            () = stop.cancelled() => return,
        };
        match published {
            Ok(p) => {
                if let ControlEvent::Alarm(news) = &*p.event {
                    let alarm = match news {
                        AlarmNews::Raised(a)
                        | AlarmNews::Cleared(a)
                        | AlarmNews::Acknowledged(a) => a,
                    };
                    events.publish(&subscriptions, alarm);
                    metrics.opcua().events(1);
                }
            }
            // A client that missed news asks ConditionRefresh.
            Err(RecvError::Lagged(_)) => {}
            Err(RecvError::Closed) => return,
        }
    }
}
