//! The address space in the server's namespace, built from [`super::spec`]:
//! the object types `DriveType` and `BusType` with their instance
//! declarations, `Objects/Drives/<drive>` and `Objects/Buses/<bus>`, each
//! variable with its `EngineeringUnits` (UNECE) and `EURange`. Drives and
//! buses are added and removed as a reload changes the plant (by
//! `render.rs`, which follows it).

use std::collections::BTreeSet;
use std::sync::Arc;
use std::time::Duration;

use opcua::server::SubscriptionCache;
use opcua::server::address_space::{
    AccessLevel, AddressSpace, DataTypeBuilder, EventNotifier, MethodBuilder, NodeType,
    ObjectBuilder, ObjectTypeBuilder, ReferenceDirection, VariableBuilder,
};
use opcua::types::{
    Argument, AttributeId, DataTypeDefinition, DataTypeId, DataValue, EUInformation,
    EnumDefinition, EnumField, ExtensionObject, LocalizedText, NodeId, ObjectId, ObjectTypeId,
    QualifiedName, Range, ReferenceTypeId, StatusCode, TimestampsToReturn, VariableTypeId, Variant,
};

use super::spec::{
    self, BUS_TYPE, BUSES, BusVariable, DRIVE_TYPE, DRIVES, Kind, MODE_TYPE, MODES, Method,
    SET_MODE_ARGUMENT, SETTINGS, Source, Unit, VARIABLES, Variable, described,
};
use super::values::missing;
use crate::plant::Directory;

/// The UNECE units' namespace (OPC UA Part 8, 5.6.3).
const UNECE: &str = "http://www.opcfoundation.org/UA/units/un/cefact";

/// The address space's own part, in namespace `ns`.
#[derive(Debug, Clone, Copy)]
pub struct Nodes {
    /// The namespace index.
    pub ns: u16,
}

/// A `Description` in the server's locale (none named: the text is
/// English).
fn text(words: &str) -> LocalizedText {
    LocalizedText::new("", words)
}

/// Where a drive is, and how often it is polled.
pub struct DriveNodes<'a> {
    /// Its name.
    pub name: &'a str,
    /// Its poll period: the variables' minimum sampling interval.
    pub period: Duration,
}

impl Nodes {
    /// The node id of `path` in the namespace.
    pub fn id(&self, path: &str) -> NodeId {
        NodeId::new(self.ns, path.to_string())
    }

    /// The data type of a variable of `kind`.
    fn data_type(&self, kind: Kind) -> NodeId {
        match kind {
            Kind::Double => DataTypeId::Double.into(),
            Kind::Int32 => DataTypeId::Int32.into(),
            Kind::UInt16 => DataTypeId::UInt16.into(),
            Kind::UInt32 => DataTypeId::UInt32.into(),
            Kind::Boolean => DataTypeId::Boolean.into(),
            Kind::String => DataTypeId::String.into(),
            Kind::Mode => self.id(MODE_TYPE),
        }
    }

    /// Builds the types and the two folders.
    pub fn build_types(&self, space: &mut AddressSpace) {
        self.mode_type(space);
        let drive_type = self.id(DRIVE_TYPE);
        ObjectTypeBuilder::new(
            &drive_type,
            QualifiedName::new(self.ns, DRIVE_TYPE),
            DRIVE_TYPE,
        )
        .description(text(described::DRIVE_TYPE))
        .subtype_of(ObjectTypeId::BaseObjectType)
        .insert(space);
        let settings = self.id(&format!("{DRIVE_TYPE}/{SETTINGS}"));
        for v in &VARIABLES {
            let path = format!("{DRIVE_TYPE}/{}", v.path());
            let parent = match v.source {
                Source::Setting(_) => {
                    // Made before its first variable: browsed after the
                    // setpoints, in the manual's order.
                    if space.find(&settings).is_none() {
                        self.settings_object(space, &settings, &drive_type, true);
                    }
                    &settings
                }
                _ => &drive_type,
            };
            self.variable(space, &path, parent, v, Duration::ZERO, true);
        }
        for m in Method::ALL {
            let path = format!("{DRIVE_TYPE}/{}", m.path());
            let parent = if m == Method::Save {
                &settings
            } else {
                &drive_type
            };
            self.method(space, &path, parent, m, true);
        }
        let bus_type = self.id(BUS_TYPE);
        ObjectTypeBuilder::new(&bus_type, QualifiedName::new(self.ns, BUS_TYPE), BUS_TYPE)
            .description(text(described::BUS_TYPE))
            .subtype_of(ObjectTypeId::BaseObjectType)
            .insert(space);
        for v in BusVariable::ALL {
            let path = format!("{BUS_TYPE}/{}", v.name());
            self.bus_variable(space, &path, &bus_type, v, true);
        }
        for (folder, description) in [(DRIVES, described::DRIVES), (BUSES, described::BUSES)] {
            ObjectBuilder::new(
                &self.id(folder),
                QualifiedName::new(self.ns, folder),
                folder,
            )
            .description(text(description))
            .is_folder()
            .organized_by(ObjectId::ObjectsFolder)
            .insert(space);
        }
    }

    /// `DriveMode`, `Mode`'s enumeration: the STATUS bits' values, each
    /// named (`EnumStrings`, and the definition OPC UA 1.04 clients read).
    fn mode_type(&self, space: &mut AddressSpace) {
        let id = self.id(MODE_TYPE);
        let fields = MODES
            .iter()
            .map(|(value, name, description)| EnumField {
                value: i64::from(*value),
                display_name: text(name),
                description: text(description),
                name: (*name).into(),
            })
            .collect();
        DataTypeBuilder::new(&id, QualifiedName::new(self.ns, MODE_TYPE), MODE_TYPE)
            .description(text(described::MODE_TYPE))
            .subtype_of(DataTypeId::Enumeration)
            .data_type_definition(DataTypeDefinition::Enum(EnumDefinition {
                fields: Some(fields),
            }))
            .insert(space);
        let strings: Vec<LocalizedText> = MODES.iter().map(|(_, name, _)| text(name)).collect();
        VariableBuilder::new(
            &self.id(&format!("{MODE_TYPE}/EnumStrings")),
            "EnumStrings",
            "EnumStrings",
        )
        .description(text("The names of DriveMode's values, 0 to 3."))
        .property_of(id)
        .has_type_definition(VariableTypeId::PropertyType)
        .data_type(DataTypeId::LocalizedText)
        .value_rank(1)
        .array_dimensions(&[MODES.len() as u32])
        .value(Variant::from(strings))
        .insert(space);
    }

    fn settings_object(&self, space: &mut AddressSpace, id: &NodeId, parent: &NodeId, decl: bool) {
        let mut b = ObjectBuilder::new(id, QualifiedName::new(self.ns, SETTINGS), SETTINGS)
            .description(text(described::SETTINGS))
            .has_type_definition(ObjectTypeId::BaseObjectType)
            .component_of(parent.clone());
        if decl {
            b = b.reference(
                ObjectId::ModellingRule_Mandatory,
                ReferenceTypeId::HasModellingRule,
                ReferenceDirection::Forward,
            );
        }
        b.insert(space);
    }

    fn variable(
        &self,
        space: &mut AddressSpace,
        path: &str,
        parent: &NodeId,
        v: &Variable,
        period: Duration,
        decl: bool,
    ) {
        let id = &self.id(path);
        let mut access = AccessLevel::CURRENT_READ;
        if v.writable() {
            access |= AccessLevel::CURRENT_WRITE;
        }
        if v.history.is_some() {
            access |= AccessLevel::HISTORY_READ;
        }
        let mut b = VariableBuilder::new(id, QualifiedName::new(self.ns, v.name), v.name)
            .description(text(v.description))
            .data_type(self.data_type(v.kind))
            .access_level(access)
            .user_access_level(access)
            .historizing(v.history.is_some())
            .minimum_sampling_interval(period.as_secs_f64() * 1000.0)
            .component_of(parent.clone())
            .has_type_definition(if v.is_analog() {
                VariableTypeId::AnalogItemType
            } else {
                VariableTypeId::BaseDataVariableType
            });
        if decl {
            b = b.has_modelling_rule(ObjectId::ModellingRule_Mandatory);
        }
        b.insert(space);
        self.properties(space, path, v.name, v.unit, v.range);
        set_missing(space, id);
    }

    /// `EngineeringUnits` and `EURange` of the variable `name` at `base`.
    fn properties(
        &self,
        space: &mut AddressSpace,
        base: &str,
        name: &str,
        unit: Option<Unit>,
        range: Option<(f64, f64)>,
    ) {
        let id = self.id(base);
        if let Some(unit) = unit {
            let eu = EUInformation {
                namespace_uri: UNECE.into(),
                unit_id: unit.unit_id(),
                display_name: LocalizedText::new("", unit.symbol),
                description: LocalizedText::new("", unit.name),
            };
            VariableBuilder::new(
                &self.id(&format!("{base}/EngineeringUnits")),
                "EngineeringUnits",
                "EngineeringUnits",
            )
            .description(text(&format!(
                "The unit of {name}: {} ({}, UNECE code {}).",
                unit.name, unit.symbol, unit.code
            )))
            .property_of(id.clone())
            .has_type_definition(VariableTypeId::PropertyType)
            .data_type(DataTypeId::EUInformation)
            .value(Variant::from(ExtensionObject::from_message(eu)))
            .insert(space);
        }
        if let Some((low, high)) = range {
            VariableBuilder::new(&self.id(&format!("{base}/EURange")), "EURange", "EURange")
                .description(text(&format!(
                    "The range of {name} the drive's register holds, in its unit."
                )))
                .property_of(id.clone())
                .has_type_definition(VariableTypeId::PropertyType)
                .data_type(DataTypeId::Range)
                .value(Variant::from(ExtensionObject::from_message(Range {
                    low,
                    high,
                })))
                .insert(space);
        }
    }

    fn method(&self, space: &mut AddressSpace, path: &str, parent: &NodeId, m: Method, decl: bool) {
        let id = &self.id(path);
        let mut b = MethodBuilder::new(id, QualifiedName::new(self.ns, m.name()), m.name())
            .description(text(m.description()))
            .component_of(parent.clone())
            .executable(true)
            .user_executable(true);
        let arguments = self.id(&format!("{path}/InputArguments"));
        if m == Method::SetMode {
            let (name, description) = SET_MODE_ARGUMENT;
            b = b.input_args(
                space,
                &arguments,
                &[Argument {
                    name: name.into(),
                    data_type: DataTypeId::String.into(),
                    value_rank: -1,
                    array_dimensions: None,
                    description: text(description),
                }],
            );
        }
        if decl {
            b = b.reference(
                ObjectId::ModellingRule_Mandatory,
                ReferenceTypeId::HasModellingRule,
                ReferenceDirection::Forward,
            );
        }
        b.insert(space);
        if let Some(node) = space.find_mut(&arguments) {
            node.as_mut_node()
                .set_description(text(&format!("What {} takes.", m.name())));
        }
    }

    fn bus_variable(
        &self,
        space: &mut AddressSpace,
        path: &str,
        parent: &NodeId,
        v: BusVariable,
        decl: bool,
    ) {
        let id = &self.id(path);
        let mut b = VariableBuilder::new(id, QualifiedName::new(self.ns, v.name()), v.name())
            .description(text(v.description()))
            .data_type(self.data_type(v.kind()))
            .access_level(AccessLevel::CURRENT_READ)
            .user_access_level(AccessLevel::CURRENT_READ)
            .component_of(parent.clone())
            .has_type_definition(if v.kind() == Kind::Double {
                VariableTypeId::AnalogItemType
            } else {
                VariableTypeId::BaseDataVariableType
            });
        if decl {
            b = b.has_modelling_rule(ObjectId::ModellingRule_Mandatory);
        }
        b.insert(space);
        let range = (v == BusVariable::Utilisation).then_some((0.0, 100.0));
        self.properties(space, path, v.name(), v.unit(), range);
        set_missing(space, id);
    }

    /// Adds `drive` under `Objects/Drives`.
    pub fn add_drive(&self, space: &mut AddressSpace, drive: &DriveNodes<'_>) {
        let id = self.id(&spec::drive_path(drive.name));
        ObjectBuilder::new(&id, QualifiedName::new(self.ns, drive.name), drive.name)
            .description(text(&format!(
                "The drive named {} in the configuration (a DriveType).",
                drive.name
            )))
            .has_type_definition(self.id(DRIVE_TYPE))
            .event_notifier(EventNotifier::SUBSCRIBE_TO_EVENTS)
            .organized_by(self.id(DRIVES))
            .insert(space);
        let settings = self.id(&format!("{}/{SETTINGS}", spec::drive_path(drive.name)));
        for v in &VARIABLES {
            let path = spec::variable_path(drive.name, v);
            let parent = match v.source {
                Source::Setting(_) => {
                    if space.find(&settings).is_none() {
                        self.settings_object(space, &settings, &id, false);
                    }
                    &settings
                }
                _ => &id,
            };
            self.variable(space, &path, parent, v, drive.period, false);
        }
        for m in Method::ALL {
            let path = spec::method_path(drive.name, m);
            let parent = if m == Method::Save { &settings } else { &id };
            self.method(space, &path, parent, m, false);
        }
    }

    /// Adds `bus` under `Objects/Buses`.
    pub fn add_bus(&self, space: &mut AddressSpace, bus: &str) {
        let id = self.id(&spec::bus_path(bus));
        ObjectBuilder::new(&id, QualifiedName::new(self.ns, bus), bus)
            .description(text(&format!(
                "The bus named {bus} in the configuration (a BusType)."
            )))
            .has_type_definition(self.id(BUS_TYPE))
            .organized_by(self.id(BUSES))
            .insert(space);
        for v in BusVariable::ALL {
            let path = format!("{}/{}", spec::bus_path(bus), v.name());
            self.bus_variable(space, &path, &id, v, false);
        }
    }

    /// Drive `drive` is polled every `period` now (a reload changed its
    /// poll rate in place): its variables say so, keeping their nodes and
    /// the clients' monitored items on them.
    pub fn set_period(&self, space: &mut AddressSpace, drive: &str, period: Duration) {
        for v in &VARIABLES {
            let id = self.id(&spec::variable_path(drive, v));
            if let Some(NodeType::Variable(node)) = space.find_mut(&id) {
                node.set_minimum_sampling_interval(period.as_secs_f64() * 1000.0);
            }
        }
    }

    /// Removes drive `drive` and every node under it.
    pub fn remove_drive(&self, space: &mut AddressSpace, drive: &str) {
        let path = spec::drive_path(drive);
        let mut paths = vec![path.clone(), format!("{path}/{SETTINGS}")];
        for v in &VARIABLES {
            let base = spec::variable_path(drive, v);
            paths.push(format!("{base}/EngineeringUnits"));
            paths.push(format!("{base}/EURange"));
            paths.push(base);
        }
        for m in Method::ALL {
            let base = spec::method_path(drive, m);
            paths.push(format!("{base}/InputArguments"));
            paths.push(base);
        }
        self.delete(space, &paths);
    }

    /// Removes bus `bus` and every node under it.
    pub fn remove_bus(&self, space: &mut AddressSpace, bus: &str) {
        let path = spec::bus_path(bus);
        let mut paths = vec![path.clone()];
        for v in BusVariable::ALL {
            let base = format!("{path}/{}", v.name());
            paths.push(format!("{base}/EngineeringUnits"));
            paths.push(format!("{base}/EURange"));
            paths.push(base);
        }
        self.delete(space, &paths);
    }

    fn delete(&self, space: &mut AddressSpace, paths: &[String]) {
        for path in paths {
            space.delete(&self.id(path), true);
        }
    }
}

/// Puts `values` into the variables of `space` and tells the
/// subscriptions that watch them (what `InMemoryNodeManager::set_values`
/// does, for the face's own tasks and requests). Variables that are not
/// there (a drive a reload removed meanwhile) are skipped. Returns how many
/// values were set.
pub fn set_values(
    space: &opcua::sync::RwLock<AddressSpace>,
    subscriptions: &SubscriptionCache,
    values: Vec<(NodeId, DataValue)>,
) -> usize {
    let mut space = space.write();
    let mut set = Vec::with_capacity(values.len());
    for (id, value) in values {
        if let Some(NodeType::Variable(v)) = space.find_mut(&id) {
            v.set_data_value(value);
            set.push(id);
        }
    }
    subscriptions.maybe_notify(
        set.iter().map(|id| (id, AttributeId::Value)),
        |id, attribute, range, encoding| {
            space.find(id)?.as_node().get_attribute(
                TimestampsToReturn::Both,
                attribute,
                range,
                encoding,
            )
        },
    );
    set.len()
}

/// The value of a variable not read yet.
fn set_missing(space: &mut AddressSpace, id: &NodeId) {
    if let Some(NodeType::Variable(v)) = space.find_mut(id) {
        v.set_data_value(missing(StatusCode::BadWaitingForInitialData));
    }
}

/// Names of the drives and buses of `directory`, with the drives' poll
/// periods (µs).
pub fn plant_of(directory: &Directory) -> (BTreeSet<(String, u64)>, BTreeSet<String>) {
    let drives = directory
        .drives()
        .filter_map(|d| {
            let handle = directory.handle_of(d)?;
            let period = handle.poll_period(d.unit);
            Some((
                d.name.clone(),
                u64::try_from(period.as_micros()).unwrap_or(u64::MAX),
            ))
        })
        .collect();
    let buses = directory
        .buses()
        .map(|b| b.handle.name().to_string())
        .collect();
    (drives, buses)
}

/// A shared handle on the address space.
pub type Space = Arc<opcua::sync::RwLock<AddressSpace>>;
