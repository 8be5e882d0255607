//! The node manager of the server's namespace: reads of what a drive holds,
//! writes of setpoints and settings, method calls, and the monitored items
//! counted for the metrics. It translates and renders only: every write
//! and call goes to the control core with the session's caller
//! ([`Sessions::caller`]), which decides, audits and answers; a refusal
//! becomes its status code with the core's words in the diagnostics
//! ([`super::outcome`]). `HistoryRead` is in [`super::history`].

use std::collections::HashMap;
use std::sync::atomic::{AtomicI64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use opcua::server::CreateMonitoredItem;
use opcua::server::address_space::AddressSpace;
use opcua::server::diagnostics::NamespaceMetadata;
use opcua::server::node_manager::memory::{InMemoryNodeManager, InMemoryNodeManagerImpl};
use opcua::server::node_manager::{
    HistoryNode, MethodCall, MonitoredItemRef, ParsedReadValueId, RequestContext, ServerContext,
    WriteNode,
};
use opcua::sync::RwLock;
use opcua::types::{
    AttributeId, DataValue, NodeId, ReadRawModifiedDetails, StatusCode, TimestampsToReturn, Variant,
};

use super::address::{Nodes, set_values};
use super::history;
use super::outcome::{self, Answer};
use super::sessions::Sessions;
use super::spec::{self, Method, Setpoint, Source, VARIABLES, Variable};
use super::users::Users;
use super::values::{held_value, missing};
use crate::control::settings::{ApplyOptions, SettingsError, SettingsReport};
use crate::control::{Caller, Control, ControlRequest, Target};
use crate::drive::settings::DriveSettings;
use crate::drive::wanted::{Document, Setting, Wanted};
use crate::drive::{ConfigCommand, DriveRequest, units};
use crate::history::History;
use crate::metrics::Metrics;

/// What the face's node manager needs.
pub struct Drives {
    nodes: Nodes,
    control: Control,
    users: Arc<Users>,
    sessions: Arc<Sessions>,
    history: Arc<History>,
    metrics: Arc<Metrics>,
    /// What each drive held when last read: read again when older than a
    /// read's `maxAge`.
    held: Mutex<HashMap<String, (Instant, DriveSettings)>>,
    /// Monitored items on the server's nodes, this manager's and the core
    /// namespace's (events).
    monitored: Arc<AtomicI64>,
}

/// The face's node manager, as the server holds it.
pub type DriveManager = InMemoryNodeManager<Drives>;

/// The drive and the variable or method a node id of the namespace names.
enum Named<'a> {
    Variable(&'a str, &'static Variable),
    Method(&'a str, Method),
}

fn named(id: &NodeId) -> Option<Named<'_>> {
    let (drive, rest) = spec::split_drive_path(spec::path_of(id)?)?;
    if let Some(v) = spec::variable_at(rest) {
        return Some(Named::Variable(drive, v));
    }
    spec::method_at(rest).map(|m| Named::Method(drive, m))
}

impl Drives {
    /// The manager of namespace `nodes`.
    pub fn new(
        nodes: Nodes,
        control: Control,
        (users, sessions): (Arc<Users>, Arc<Sessions>),
        history: Arc<History>,
        metrics: Arc<Metrics>,
        monitored: Arc<AtomicI64>,
    ) -> Self {
        Drives {
            nodes,
            control,
            users,
            sessions,
            history,
            metrics,
            held: Mutex::new(HashMap::new()),
            monitored,
        }
    }

    /// The namespace.
    pub fn nodes(&self) -> Nodes {
        self.nodes
    }

    fn caller(&self, context: &RequestContext) -> Result<Caller, Answer> {
        let identity = self.users.identity(context.user_token());
        self.sessions.caller(context, &identity)
    }

    fn target(&self, drive: &str) -> Result<Target, Answer> {
        self.control.target(drive).map_err(|e| {
            Answer::new(
                StatusCode::BadNodeIdUnknown,
                format!("{e}: the drive was removed from the configuration"),
            )
        })
    }

    /// What `drive` holds, read from it unless read within `max_age`.
    async fn held(
        &self,
        context: &RequestContext,
        drive: &str,
        max_age: Duration,
    ) -> Result<DriveSettings, StatusCode> {
        if let Some((at, held)) = self.lock_held().get(drive)
            && at.elapsed() <= max_age
        {
            return Ok(*held);
        }
        let target = self.target(drive).map_err(|a| a.status)?;
        let identity = self.users.identity(context.user_token());
        let caller = Caller::new(
            crate::control::Face::OpcUa,
            super::sessions::who_of(context, &identity),
            identity.role.unwrap_or(crate::control::Role::Viewer),
            crate::bus::SourceId::new_unique(),
        );
        let held = self
            .control
            .read_settings(&caller, target)
            .await
            .map_err(|e| outcome::bus_status(&e))?;
        self.lock_held()
            .insert(drive.to_string(), (Instant::now(), held));
        Ok(held)
    }

    fn lock_held(&self) -> std::sync::MutexGuard<'_, HashMap<String, (Instant, DriveSettings)>> {
        self.held.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The values of `drive`'s held variables in `held`, stamped now.
    fn held_values(&self, drive: &str, held: &DriveSettings) -> Vec<(NodeId, DataValue)> {
        let now = std::time::SystemTime::now();
        VARIABLES
            .iter()
            .filter_map(|v| {
                let value = held_value(v, held)?;
                Some((
                    self.nodes.id(&spec::variable_path(drive, v)),
                    super::values::data_value(value, StatusCode::Good, now),
                ))
            })
            .collect()
    }

    /// One write of a variable, through the core: the value the variable
    /// holds once the drive confirmed it, or the answer to put on the write.
    async fn write_one(
        &self,
        context: &RequestContext,
        node: &WriteNode,
    ) -> Result<Option<(NodeId, DataValue)>, Answer> {
        let value = node.value();
        let Some(Named::Variable(drive, variable)) = named(&value.node_id) else {
            return Err(Answer::new(
                StatusCode::BadNodeIdUnknown,
                "no such variable",
            ));
        };
        if !variable.writable() {
            return Err(Answer::new(
                StatusCode::BadNotWritable,
                format!("{} is read only", variable.name),
            ));
        }
        if value.attribute_id != AttributeId::Value || !value.index_range.is_none() {
            return Err(Answer::new(
                StatusCode::BadWriteNotSupported,
                "only the Value attribute is written, whole",
            ));
        }
        let written = value.value.value.clone().unwrap_or(Variant::Empty);
        let caller = self.caller(context)?;
        let target = self.target(drive)?;
        match variable.source {
            Source::Setpoint(setpoint) => {
                let request = setpoint_request(setpoint, variable, &written)
                    .map_err(|u| self.unmade(&caller, target, u))?;
                self.control
                    .write(&caller, target, ControlRequest::drive(request))
                    .await
                    .map_err(|f| outcome::failure(&f))?;
            }
            Source::Setting(setting) => {
                let document = document(setting, variable, &written)
                    .map_err(|u| self.unmade(&caller, target, u))?;
                self.apply(&caller, target, &document).await?;
            }
            Source::Status(_) | Source::Online => unreachable!("not writable"),
        }
        // Confirmed: the variable holds what was written; the next read
        // asks the drive again.
        self.lock_held().remove(drive);
        Ok(number_of(variable, &written).map(|v| {
            let now = std::time::SystemTime::now();
            (
                value.node_id.clone(),
                super::values::data_value(v, StatusCode::Good, now),
            )
        }))
    }

    /// The answer to a write that could not be made into a request, once
    /// the core audited it as refused.
    fn unmade(&self, caller: &Caller, target: Target, unmade: Unmade) -> Answer {
        self.control.refused(
            caller,
            target,
            unmade.what,
            format!("refused: {}", unmade.answer.text),
        );
        unmade.answer
    }

    /// `Settings.Save()`: what the drive holds, written again with its
    /// save flags (the core's still-check applies: refused while the motor
    /// turns).
    async fn save(&self, caller: &Caller, target: Target) -> Result<(), Answer> {
        let held = self
            .control
            .read_settings(caller, target)
            .await
            .map_err(|e| Answer::new(outcome::bus_status(&e), e.to_string()))?;
        let options = ApplyOptions {
            save: true,
            ..ApplyOptions::default()
        };
        let report = self
            .control
            .apply_wanted(caller, target, &Wanted::of(&held), options)
            .await;
        settled(report)
    }

    async fn apply(
        &self,
        caller: &Caller,
        target: Target,
        document: &Document,
    ) -> Result<(), Answer> {
        let report = self
            .control
            .apply_settings(caller, target, document, ApplyOptions::default())
            .await;
        settled(report)
    }
}

/// What a settings operation came to.
fn settled(report: Result<SettingsReport, SettingsError>) -> Result<(), Answer> {
    let report = report.map_err(|e| match e {
        SettingsError::Invalid(refused) => Answer::new(
            StatusCode::BadOutOfRange,
            refused
                .iter()
                .map(|r| r.detail.as_str())
                .collect::<Vec<_>>()
                .join("; "),
        ),
        SettingsError::Failed(f) => outcome::failure(&f),
    })?;
    match &report.failure {
        None if report.complete() => Ok(()),
        Some(f) => Err(outcome::failure(f)),
        None => Err(Answer::new(StatusCode::BadDeviceFailure, report.words())),
    }
}

impl Drives {
    /// One method call, through the core.
    async fn call_one(&self, context: &RequestContext, call: &MethodCall) -> Result<(), Answer> {
        let Some(Named::Method(drive, method)) = named(call.method_id()) else {
            return Err(Answer::new(StatusCode::BadMethodInvalid, "no such method"));
        };
        let object = self.nodes.id(&spec::method_object_path(drive, method));
        if *call.object_id() != object {
            return Err(Answer::new(
                StatusCode::BadMethodInvalid,
                format!(
                    "{} is a method of {}, not of this object",
                    method.name(),
                    spec::method_object_path(drive, method)
                ),
            ));
        }
        let caller = self.caller(context)?;
        let target = self.target(drive)?;
        let command = match method {
            Method::Activate => ConfigCommand::Activate,
            Method::Deactivate => ConfigCommand::Deactivate,
            Method::Brake => ConfigCommand::EmergencyBrake,
            Method::FaultReset => ConfigCommand::FaultReset,
            Method::SetMode => {
                mode(call.arguments()).map_err(|u| self.unmade(&caller, target, u))?
            }
            Method::Save => return self.save(&caller, target).await,
        };
        self.control
            .write(
                &caller,
                target,
                ControlRequest::drive(DriveRequest::Config(command)),
            )
            .await
            .map(|_| ())
            .map_err(|f| outcome::failure(&f))
    }
}

/// A write or call refused before it became a request: the answer, and
/// what was asked for in words, for the audit.
struct Unmade {
    answer: Answer,
    what: String,
}

impl Unmade {
    fn new(answer: Answer, what: String) -> Self {
        Unmade { answer, what }
    }

    /// A value outside the drive's range.
    fn range(e: &crate::drive::RangeError) -> Self {
        Unmade::new(outcome::out_of_range(e), e.attempted())
    }
}

/// `SetMode`'s mode: one String, a mode the drive has.
fn mode(arguments: &[Variant]) -> Result<ConfigCommand, Unmade> {
    let modes = ConfigCommand::modes_in_words();
    match arguments {
        [Variant::String(s)] => {
            let s = s.as_ref();
            ConfigCommand::mode_named(s).ok_or_else(|| {
                Unmade::new(
                    Answer::new(
                        StatusCode::BadInvalidArgument,
                        format!("SetMode(\"{s}\"): \"{s}\" is not a mode of the drive: the mode is {modes}"),
                    ),
                    format!("mode \"{s}\""),
                )
            })
        }
        other => Err(Unmade::new(
            Answer::new(
                StatusCode::BadInvalidArgument,
                format!("SetMode takes one String: {modes}"),
            ),
            format!("SetMode with {}", show(other)),
        )),
    }
}

/// Arguments or a value as the audit shows them.
fn show(values: &[Variant]) -> String {
    let shown: Vec<String> = values.iter().map(|v| format!("{v:?}")).collect();
    format!("({})", shown.join(", "))
}

/// A written value as a number, whatever numeric type the client sent.
fn as_f64(value: &Variant) -> Option<f64> {
    match value {
        Variant::Double(v) => Some(*v),
        Variant::Float(v) => Some(f64::from(*v)),
        Variant::SByte(v) => Some(f64::from(*v)),
        Variant::Byte(v) => Some(f64::from(*v)),
        Variant::Int16(v) => Some(f64::from(*v)),
        Variant::UInt16(v) => Some(f64::from(*v)),
        Variant::Int32(v) => Some(f64::from(*v)),
        Variant::UInt32(v) => Some(f64::from(*v)),
        Variant::Int64(v) => Some(*v as f64),
        Variant::UInt64(v) => Some(*v as f64),
        _ => None,
    }
}

fn type_mismatch(variable: &Variable, value: &Variant) -> Unmade {
    Unmade::new(
        Answer::new(
            StatusCode::BadTypeMismatch,
            format!(
                "{} takes a number (Double), not {:?}",
                variable.name,
                value.type_id()
            ),
        ),
        format!("{} = {}", variable.name, show(std::slice::from_ref(value))),
    )
}

/// The drive request of a setpoint write, its value checked against the
/// drive's range (the range in the refusal).
fn setpoint_request(
    setpoint: Setpoint,
    variable: &Variable,
    value: &Variant,
) -> Result<DriveRequest, Unmade> {
    let v = as_f64(value).ok_or_else(|| type_mismatch(variable, value))?;
    let range = |e: crate::drive::RangeError| Unmade::range(&e);
    Ok(match setpoint {
        Setpoint::Speed => DriveRequest::Speed {
            rpm: units::speed_setpoint(v).map_err(range)?,
        },
        Setpoint::Position => DriveRequest::Position {
            centideg: units::position_setpoint(v).map_err(range)?,
        },
        Setpoint::Torque => DriveRequest::Torque {
            counts: units::torque_setpoint(v).map_err(range)?,
        },
    })
}

/// The settings document of one setting's write.
fn document(setting: Setting, variable: &Variable, value: &Variant) -> Result<Document, Unmade> {
    let mut d = Document::default();
    let what = || format!("{} = {}", variable.name, show(std::slice::from_ref(value)));
    if setting == Setting::Rs485Control {
        let Variant::Boolean(on) = value else {
            return Err(Unmade::new(
                Answer::new(StatusCode::BadTypeMismatch, "Rs485Control takes a Boolean"),
                what(),
            ));
        };
        d.rs485_control = Some(*on);
        return Ok(d);
    }
    let v = as_f64(value).ok_or_else(|| type_mismatch(variable, value))?;
    let whole = || {
        if v.fract() == 0.0 && v.is_finite() {
            Ok(v as i64)
        } else {
            Err(Unmade::new(
                Answer::new(
                    StatusCode::BadOutOfRange,
                    format!("{} takes a whole number, not {v}", variable.name),
                ),
                what(),
            ))
        }
    };
    match setting {
        Setting::CurrentLimit => d.limit_a = Some(v),
        Setting::StallTime => d.stall_ms = Some(whole()?),
        Setting::SpeedRamp => d.speed_alpha = Some(whole()?),
        Setting::PositionRamp => d.position_alpha = Some(whole()?),
        Setting::InertiaRatio => d.inertia_ratio = Some(whole()?),
        Setting::Rs485Control => {}
    }
    Ok(d)
}

/// The value a variable holds once `written` was confirmed.
fn number_of(variable: &Variable, written: &Variant) -> Option<Variant> {
    match written {
        Variant::Boolean(_) => Some(written.clone()),
        other => as_f64(other).map(|v| super::values::number(variable.kind, v)),
    }
}

#[async_trait]
impl InMemoryNodeManagerImpl for Drives {
    async fn init(&self, _space: &mut AddressSpace, _context: ServerContext) {}

    fn name(&self) -> &str {
        "drivegate"
    }

    fn namespaces(&self) -> Vec<NamespaceMetadata> {
        vec![NamespaceMetadata {
            namespace_uri: spec::NAMESPACE.to_string(),
            namespace_index: self.nodes.ns,
            ..Default::default()
        }]
    }

    /// What a drive holds (its setpoints and settings) is read from it,
    /// unless read within the request's `maxAge`; the rest is what the
    /// face put in the address space.
    async fn read_values(
        &self,
        context: &RequestContext,
        space: &RwLock<AddressSpace>,
        nodes: &[&ParsedReadValueId],
        max_age: f64,
        timestamps: TimestampsToReturn,
    ) -> Vec<DataValue> {
        let max_age = Duration::from_secs_f64((max_age / 1000.0).clamp(0.0, 3600.0));
        let mut read = Vec::new();
        for node in nodes {
            if node.attribute_id == AttributeId::Value
                && let Some(Named::Variable(drive, v)) = named(&node.node_id)
                && !read.iter().any(|d: &String| d == drive)
                && matches!(v.source, Source::Setpoint(_) | Source::Setting(_))
            {
                read.push(drive.to_string());
            }
        }
        for drive in read {
            let values = match self.held(context, &drive, max_age).await {
                Ok(held) => self.held_values(&drive, &held),
                Err(status) => VARIABLES
                    .iter()
                    .filter(|v| matches!(v.source, Source::Setpoint(_) | Source::Setting(_)))
                    .map(|v| {
                        (
                            self.nodes.id(&spec::variable_path(&drive, v)),
                            missing(status),
                        )
                    })
                    .collect(),
            };
            let n = set_values(space, context.subscriptions(), values);
            self.metrics.opcua().values_published(n);
        }
        let space = space.read();
        nodes
            .iter()
            .map(|n| space.read(context, n, 0.0, timestamps))
            .collect()
    }

    async fn write(
        &self,
        context: &RequestContext,
        space: &RwLock<AddressSpace>,
        nodes: &mut [&mut WriteNode],
    ) -> Result<(), StatusCode> {
        for node in nodes {
            match self.write_one(context, node).await {
                Ok(written) => {
                    let n = set_values(
                        space,
                        context.subscriptions(),
                        written.into_iter().collect(),
                    );
                    self.metrics.opcua().values_published(n);
                    node.set_status(StatusCode::Good);
                }
                Err(answer) => {
                    node.set_status(answer.status);
                    node.set_diagnostic_info(answer.diagnostic());
                }
            }
        }
        Ok(())
    }

    async fn call(
        &self,
        context: &RequestContext,
        _space: &RwLock<AddressSpace>,
        calls: &mut [&mut &mut MethodCall],
    ) -> Result<(), StatusCode> {
        for call in calls {
            match self.call_one(context, call).await {
                Ok(()) => call.set_status(StatusCode::Good),
                Err(answer) => {
                    if answer.status == StatusCode::BadInvalidArgument {
                        call.set_argument_error(vec![StatusCode::BadInvalidArgument]);
                    }
                    call.set_status(answer.status);
                    call.set_diagnostic_info(answer.diagnostic());
                }
            }
        }
        Ok(())
    }

    async fn history_read_raw_modified(
        &self,
        _context: &RequestContext,
        details: &ReadRawModifiedDetails,
        nodes: &mut [&mut &mut HistoryNode],
        _timestamps: TimestampsToReturn,
    ) -> Result<(), StatusCode> {
        if details.is_read_modified {
            return Err(StatusCode::BadHistoryOperationUnsupported);
        }
        let plant = self.control.plant().now();
        for node in nodes {
            let found = match named(node.node_id()) {
                Some(Named::Variable(drive, v)) => v.history.and_then(|field| {
                    let (d, handle) = plant.drive(drive).ok()?;
                    Some((handle.name_arc(), d.unit, field))
                }),
                _ => None,
            };
            match found {
                Some((bus, unit, field)) => {
                    history::read_raw(&self.history, (&bus, unit, field), details, node)
                }
                None => node.set_status(StatusCode::BadHistoryOperationUnsupported),
            }
        }
        Ok(())
    }

    async fn create_value_monitored_items(
        &self,
        context: &RequestContext,
        space: &RwLock<AddressSpace>,
        items: &mut [&mut &mut CreateMonitoredItem],
    ) {
        let to_read: Vec<_> = items.iter().map(|r| r.item_to_monitor()).collect();
        let values = self
            .read_values(context, space, &to_read, 0.0, TimestampsToReturn::Both)
            .await;
        for (value, item) in values.into_iter().zip(items.iter_mut()) {
            if value.status() != StatusCode::BadAttributeIdInvalid {
                item.set_initial_value(value);
            }
            item.set_status(StatusCode::Good);
        }
        self.count(items.len() as i64);
    }

    async fn create_event_monitored_items(
        &self,
        _context: &RequestContext,
        _space: &RwLock<AddressSpace>,
        items: &mut [&mut &mut CreateMonitoredItem],
    ) {
        self.count(items.len() as i64);
    }

    async fn delete_monitored_items(&self, _context: &RequestContext, items: &[&MonitoredItemRef]) {
        self.count(-(items.len() as i64));
    }
}

impl Drives {
    fn count(&self, delta: i64) {
        let n = self.monitored.fetch_add(delta, Ordering::Relaxed) + delta;
        self.metrics.opcua().monitored_items(n);
    }
}
