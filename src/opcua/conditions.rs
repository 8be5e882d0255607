//! The crate's core node manager (namespace 0), with what conditions need
//! and the crate has not: the calls of `AcknowledgeableConditionType`'s
//! `Acknowledge` (i=9111) and `ConditionType`'s `ConditionRefresh`
//! (i=3875) are taken before the core sees them (it would refuse them,
//! having no condition instances); everything else goes to the core as it
//! came.
//!
//! `Acknowledge(EventId, Comment)` on `Alarms/<number>` must name the
//! alarm's latest EventId (`BadEventIdUnknown` otherwise), and is the core's
//! acknowledgement (`Control::acknowledge_alarm`, with the session's
//! caller: the same as the API's, audited alike); the alarm book's news
//! then publishes the acknowledged state. `ConditionRefresh` sends
//! RefreshStart, every alarm still retained (active, or not acknowledged)
//! and RefreshEnd to the event items of the caller's subscription.

use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::{Arc, OnceLock};

use async_trait::async_trait;
use opcua::core_namespace::events::{RefreshEndEventType, RefreshStartEventType};
use opcua::nodes::NamespaceMap;
use opcua::server::CreateMonitoredItem;
use opcua::server::address_space::DefaultTypeTree;
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::{
    AddNodeItem, AddReferenceItem, BrowseNode, BrowsePathItem, DeleteNodeItem, DeleteReferenceItem,
    DynNodeManager, ExternalReferenceRequest, HistoryNode, HistoryUpdateNode, MethodCall,
    MonitoredItemRef, MonitoredItemUpdateRef, NodeManager, QueryRequest, ReadNode,
    RegisterNodeItem, RequestContext, ServerContext, WriteNode,
};
use opcua::types::{
    AttributeId, ByteString, ExpandedNodeId, MethodId, MonitoringMode, NodeId,
    ReadAnnotationDataDetails, ReadAtTimeDetails, ReadEventDetails, ReadProcessedDetails,
    ReadRawModifiedDetails, StatusCode, TimestampsToReturn, Variant,
};

use super::alarms::{AlarmEvent, AlarmEvents};
use super::outcome::{self, Answer};
use super::sessions::Sessions;
use super::users::Users;
use crate::control::{AlarmError, Control, Failure};
use crate::metrics::Metrics;

/// The core node manager, wrapped.
pub struct CoreWithConditions {
    /// The crate's own.
    pub core: Arc<DynNodeManager>,
    /// The core's alarms.
    pub control: Control,
    /// Who a session is.
    pub users: Arc<Users>,
    /// The sessions' callers.
    pub sessions: Arc<Sessions>,
    /// The alarms' events (set once the namespace is built).
    pub events: Arc<OnceLock<Arc<AlarmEvents>>>,
    /// Monitored items, for the metrics.
    pub monitored: Arc<AtomicI64>,
    /// The metrics.
    pub metrics: Arc<Metrics>,
}

impl CoreWithConditions {
    async fn acknowledge(&self, context: &RequestContext, call: &mut MethodCall) {
        if let Err(answer) = self.try_acknowledge(context, call).await {
            call.set_status(answer.status);
            call.set_diagnostic_info(answer.diagnostic());
        } else {
            call.set_status(StatusCode::Good);
        }
    }

    async fn try_acknowledge(
        &self,
        context: &RequestContext,
        call: &MethodCall,
    ) -> Result<(), Answer> {
        let events = self.events.get().ok_or_else(|| {
            Answer::new(
                StatusCode::BadInternalError,
                "the server is not started yet",
            )
        })?;
        let alarm = events.alarm_of(call.object_id()).ok_or_else(|| {
            Answer::new(
                StatusCode::BadNodeIdUnknown,
                "not one of this server's conditions",
            )
        })?;
        let event_id = match call.arguments() {
            [Variant::ByteString(e), ..] => e.clone(),
            _ => {
                return Err(Answer::new(
                    StatusCode::BadInvalidArgument,
                    "Acknowledge takes the EventId (ByteString) and a comment (LocalizedText)",
                ));
            }
        };
        let Some(current) = self.control.alarms().get(alarm) else {
            return Err(Answer::new(
                StatusCode::BadNodeIdUnknown,
                format!("no alarm {alarm} (any more)"),
            ));
        };
        if current.ack.is_some() {
            return Err(Answer::new(
                StatusCode::BadConditionBranchAlreadyAcked,
                format!("alarm {alarm} is acknowledged already"),
            ));
        }
        if !events.is_latest(alarm, event_id.as_ref()) {
            return Err(Answer::new(
                StatusCode::BadEventIdUnknown,
                format!(
                    "not the latest event of alarm {alarm}: refresh (ConditionRefresh) and acknowledge that"
                ),
            ));
        }
        let identity = self.users.identity(context.user_token());
        let caller = self.sessions.caller(context, &identity)?;
        match self.control.acknowledge_alarm(&caller, alarm).await {
            Ok(_) => Ok(()),
            Err(AlarmError::Refused(r)) => Err(outcome::failure(&Failure::Refused(r))),
            Err(AlarmError::Unknown(e)) => {
                Err(Answer::new(StatusCode::BadNodeIdUnknown, e.to_string()))
            }
        }
    }

    /// RefreshStart, every retained alarm, RefreshEnd, to the event items
    /// of the caller's subscription.
    fn refresh(&self, context: &RequestContext, call: &mut MethodCall) {
        let Some(events) = self.events.get() else {
            call.set_status(StatusCode::BadInternalError);
            return;
        };
        let Some(Variant::UInt32(subscription)) = call.arguments().first().cloned() else {
            call.set_status(StatusCode::BadInvalidArgument);
            return;
        };
        let Some(subscriptions) = context
            .subscriptions()
            .get_session_subscriptions(context.session_id())
        else {
            call.set_status(StatusCode::BadSubscriptionIdInvalid);
            return;
        };
        let namespaces = NamespaceMap::new();
        let start = RefreshStartEventType::new_event_now(
            RefreshStartEventType::event_type_id(),
            ByteString::from(b"refresh-start".to_vec()),
            "",
            &namespaces,
        );
        let end = RefreshEndEventType::new_event_now(
            RefreshEndEventType::event_type_id(),
            ByteString::from(b"refresh-end".to_vec()),
            "",
            &namespaces,
        );
        let retained: Vec<AlarmEvent> = self
            .control
            .alarms()
            .list()
            .iter()
            .filter(|a| a.active() || a.ack.is_none())
            .map(|a| events.event(a))
            .collect();
        let type_tree = context.get_type_tree_for_user();
        let mut subscriptions = subscriptions.lock();
        let Some(sub) = subscriptions.get_mut(subscription) else {
            call.set_status(StatusCode::BadSubscriptionIdInvalid);
            return;
        };
        let items: Vec<u32> = sub
            .items()
            .filter(|i| i.item_to_monitor().attribute_id == AttributeId::EventNotifier)
            .map(|i| i.id())
            .collect();
        for item in items {
            sub.notify_event(&item, &start, type_tree.get());
            for ev in &retained {
                sub.notify_event(&item, ev, type_tree.get());
            }
            sub.notify_event(&item, &end, type_tree.get());
        }
        self.metrics.opcua().events(retained.len());
        call.set_status(StatusCode::Good);
    }

    fn count(&self, delta: i64) {
        let n = self.monitored.fetch_add(delta, Ordering::Relaxed) + delta;
        self.metrics.opcua().monitored_items(n);
    }
}

#[async_trait]
impl NodeManager for CoreWithConditions {
    fn owns_node(&self, id: &NodeId) -> bool {
        self.core.owns_node(id)
    }
    fn name(&self) -> &str {
        self.core.name()
    }
    fn owns_server_events(&self) -> bool {
        self.core.owns_server_events()
    }
    fn handle_new_node(&self, parent_id: &ExpandedNodeId) -> bool {
        self.core.handle_new_node(parent_id)
    }
    fn namespaces_for_user(&self, context: &RequestContext) -> Vec<NamespaceMetadata> {
        self.core.namespaces_for_user(context)
    }
    async fn init(&self, type_tree: &mut DefaultTypeTree, context: ServerContext) {
        self.core.init(type_tree, context).await
    }
    async fn resolve_external_references(
        &self,
        context: &RequestContext,
        items: &mut [&mut ExternalReferenceRequest],
    ) {
        self.core.resolve_external_references(context, items).await
    }
    async fn read(
        &self,
        context: &RequestContext,
        max_age: f64,
        ttr: TimestampsToReturn,
        nodes: &mut [&mut ReadNode],
    ) -> Result<(), StatusCode> {
        self.core.read(context, max_age, ttr, nodes).await
    }
    async fn history_read_raw_modified(
        &self,
        context: &RequestContext,
        details: &ReadRawModifiedDetails,
        nodes: &mut [&mut HistoryNode],
        ttr: TimestampsToReturn,
    ) -> Result<(), StatusCode> {
        self.core
            .history_read_raw_modified(context, details, nodes, ttr)
            .await
    }
    async fn history_read_processed(
        &self,
        context: &RequestContext,
        details: &ReadProcessedDetails,
        nodes: &mut [&mut HistoryNode],
        ttr: TimestampsToReturn,
    ) -> Result<(), StatusCode> {
        self.core
            .history_read_processed(context, details, nodes, ttr)
            .await
    }
    async fn history_read_at_time(
        &self,
        context: &RequestContext,
        details: &ReadAtTimeDetails,
        nodes: &mut [&mut HistoryNode],
        ttr: TimestampsToReturn,
    ) -> Result<(), StatusCode> {
        self.core
            .history_read_at_time(context, details, nodes, ttr)
            .await
    }
    async fn history_read_events(
        &self,
        context: &RequestContext,
        details: &ReadEventDetails,
        nodes: &mut [&mut HistoryNode],
        ttr: TimestampsToReturn,
    ) -> Result<(), StatusCode> {
        self.core
            .history_read_events(context, details, nodes, ttr)
            .await
    }
    async fn history_read_annotations(
        &self,
        context: &RequestContext,
        details: &ReadAnnotationDataDetails,
        nodes: &mut [&mut HistoryNode],
        ttr: TimestampsToReturn,
    ) -> Result<(), StatusCode> {
        self.core
            .history_read_annotations(context, details, nodes, ttr)
            .await
    }
    async fn write(
        &self,
        context: &RequestContext,
        nodes: &mut [&mut WriteNode],
    ) -> Result<(), StatusCode> {
        self.core.write(context, nodes).await
    }
    async fn history_update(
        &self,
        context: &RequestContext,
        nodes: &mut [&mut HistoryUpdateNode],
    ) -> Result<(), StatusCode> {
        self.core.history_update(context, nodes).await
    }
    async fn browse(
        &self,
        context: &RequestContext,
        nodes: &mut [BrowseNode],
    ) -> Result<(), StatusCode> {
        self.core.browse(context, nodes).await
    }
    async fn translate_browse_paths_to_node_ids(
        &self,
        context: &RequestContext,
        nodes: &mut [&mut BrowsePathItem],
    ) -> Result<(), StatusCode> {
        self.core
            .translate_browse_paths_to_node_ids(context, nodes)
            .await
    }
    async fn register_nodes(
        &self,
        context: &RequestContext,
        nodes: &mut [&mut RegisterNodeItem],
    ) -> Result<(), StatusCode> {
        self.core.register_nodes(context, nodes).await
    }
    async fn unregister_nodes(
        &self,
        context: &RequestContext,
        nodes: &[&NodeId],
    ) -> Result<(), StatusCode> {
        self.core.unregister_nodes(context, nodes).await
    }
    async fn create_monitored_items(
        &self,
        context: &RequestContext,
        items: &mut [&mut CreateMonitoredItem],
    ) -> Result<(), StatusCode> {
        self.count(items.len() as i64);
        self.core.create_monitored_items(context, items).await
    }
    async fn modify_monitored_items(
        &self,
        context: &RequestContext,
        items: &[&MonitoredItemUpdateRef],
    ) {
        self.core.modify_monitored_items(context, items).await
    }
    async fn set_monitoring_mode(
        &self,
        context: &RequestContext,
        mode: MonitoringMode,
        items: &[&MonitoredItemRef],
    ) {
        self.core.set_monitoring_mode(context, mode, items).await
    }
    async fn delete_monitored_items(&self, context: &RequestContext, items: &[&MonitoredItemRef]) {
        self.count(-(items.len() as i64));
        self.core.delete_monitored_items(context, items).await
    }
    async fn query(
        &self,
        context: &RequestContext,
        request: &mut QueryRequest,
    ) -> Result<(), StatusCode> {
        self.core.query(context, request).await
    }
    async fn call(
        &self,
        context: &RequestContext,
        calls: &mut [&mut MethodCall],
    ) -> Result<(), StatusCode> {
        let ack: NodeId = MethodId::AcknowledgeableConditionType_Acknowledge.into();
        let refresh: NodeId = MethodId::ConditionType_ConditionRefresh.into();
        let mut rest = Vec::new();
        for call in calls.iter_mut() {
            if *call.method_id() == ack {
                self.acknowledge(context, call).await;
            } else if *call.method_id() == refresh {
                self.refresh(context, call);
            } else {
                rest.push(&mut **call);
            }
        }
        if rest.is_empty() {
            return Ok(());
        }
        self.core.call(context, &mut rest).await
    }
    async fn add_nodes(
        &self,
        context: &RequestContext,
        nodes: &mut [&mut AddNodeItem],
    ) -> Result<(), StatusCode> {
        self.core.add_nodes(context, nodes).await
    }
    async fn add_references(
        &self,
        context: &RequestContext,
        refs: &mut [&mut AddReferenceItem],
    ) -> Result<(), StatusCode> {
        self.core.add_references(context, refs).await
    }
    async fn delete_nodes(
        &self,
        context: &RequestContext,
        nodes: &mut [&mut DeleteNodeItem],
    ) -> Result<(), StatusCode> {
        self.core.delete_nodes(context, nodes).await
    }
    async fn delete_node_references(
        &self,
        context: &RequestContext,
        to_delete: &[&DeleteNodeItem],
    ) {
        self.core.delete_node_references(context, to_delete).await
    }
    async fn delete_references(
        &self,
        context: &RequestContext,
        refs: &mut [&mut DeleteReferenceItem],
    ) -> Result<(), StatusCode> {
        self.core.delete_references(context, refs).await
    }
}
