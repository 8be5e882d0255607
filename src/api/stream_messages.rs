//! The stream's messages, both ways: what the server sends
//! ([`ServerMessage`]: the news about one drive every face with messages
//! sends, [`DriveMessage`], beside the stream's own, [`StreamMessage`]) and
//! what a client sends ([`ClientMessage`]).

use std::borrow::Cow;

use axum::extract::ws::Utf8Bytes;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use utoipa::openapi::RefOr;
use utoipa::openapi::schema::{OneOfBuilder, Schema};
use utoipa::{PartialSchema, ToSchema};

use super::problem_response::{Problem, ProblemDetails};
use super::settings_diff::{DeclaredState, SettingsDiff};
use crate::faces_shared::messages::DriveMessage;
use crate::faces_shared::status::StatusView;
use crate::scope::result::ScopeState;

/// A message the server sends on the stream.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(untagged)]
pub enum ServerMessage {
    /// News about one drive, as every face with messages sends it.
    Drive(DriveMessage),
    /// The stream's own.
    Stream(StreamMessage),
}

/// The messages only the stream sends: statuses as they are polled, the
/// buses, every write, settings, the scope, and the session's own.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
#[serde(tag = "type", rename_all = "kebab-case")]
pub enum StreamMessage {
    /// A drive's status was read (by its poll, or on request).
    Status {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
        /// When it was read (RFC 3339, UTC).
        seen_at: String,
        /// The decoded status (same fields as the REST status).
        status: StatusView,
    },
    /// A bus's serial port opened.
    BusUp {
        /// Bus name.
        bus: String,
    },
    /// A bus's serial port failed; drivegate reopens it.
    BusDown {
        /// Bus name.
        bus: String,
        /// Why.
        reason: String,
    },
    /// A write to a drive, from any client or face (REST, stream, Modbus
    /// TCP) or from drivegate itself (a lease's stop, the shutdown stop),
    /// once the drive answered or the write failed: the audit log's line.
    Write {
        /// Drive name; `null` for a broadcast (unit 0) or a unit that is
        /// not configured.
        drive: Option<String>,
        /// Its bus.
        bus: String,
        /// The unit written to (0: broadcast).
        unit: u8,
        /// Who sent it: a token name, a client address, or
        /// `lease-expiry (<owner>)`, `shutdown`.
        who: String,
        /// What was written, in words, with the registers and raw values.
        what: String,
        /// True when the drive confirmed it.
        ok: bool,
        /// The drive's answer, or why the write failed.
        answer: String,
        /// When (RFC 3339, UTC).
        at: String,
    },
    /// A drive with declared settings (`[bus.drive.settings]`) was
    /// compared with them: when it came online (start, a power cycle, a
    /// replaced drive), after a settings document was put on it, or while
    /// drivegate applies them (`on-drift`).
    SettingsDrift {
        /// Drive name.
        drive: String,
        /// Its bus.
        bus: String,
        /// Its unit address.
        unit: u8,
        /// The declaration's state, as in the drive's `declared_settings`
        /// (`drift`: true when it does not hold them).
        #[serde(flatten)]
        declared: DeclaredState,
        /// When (RFC 3339, UTC).
        at: String,
    },
    /// A settings document was put on a drive (from any face, or by
    /// drivegate for a declaration): what each setting was and is. Its
    /// writes come as `write` messages too.
    SettingsApplied {
        /// Who sent it (`declared-settings`: drivegate itself).
        who: String,
        /// The diff, as `PUT .../settings` answers it.
        #[serde(flatten)]
        diff: SettingsDiff,
        /// When (RFC 3339, UTC).
        at: String,
    },
    /// A scope capture was armed, triggered, ended, or filled some more
    /// (every 100 ms while it runs): its state, as `GET
    /// /api/v1/buses/{bus}/scope` shows it. Sent to every client
    /// subscribed to at least one drive.
    Scope(ScopeState),
    /// This client fell behind: `missed` updates were skipped for it.
    Lagged {
        /// Messages skipped.
        missed: u64,
    },
    /// The drives this client now receives.
    Subscribed {
        /// Drive names.
        drives: Vec<String>,
        /// What the daemon did to these drives when it started, from the
        /// safety journal the last process left (a lease kept, a stop owed
        /// by a lease whose holder is gone or whose time ran out, a brake
        /// that holds); absent when it owed nothing.
        #[serde(skip_serializing_if = "Vec::is_empty")]
        restart: Vec<RestartDecision>,
    },
    /// A message from the client could not be understood.
    Error {
        /// What was wrong.
        #[schema(value_type = ProblemDetails)]
        problem: Problem,
    },
}

impl ServerMessage {
    /// The message as a WebSocket text payload.
    pub fn to_text(&self) -> Utf8Bytes {
        json_text(self)
    }
}

impl From<DriveMessage> for ServerMessage {
    fn from(message: DriveMessage) -> Self {
        ServerMessage::Drive(message)
    }
}

impl From<StreamMessage> for ServerMessage {
    fn from(message: StreamMessage) -> Self {
        ServerMessage::Stream(message)
    }
}

impl StreamMessage {
    /// The message as a WebSocket text payload.
    pub fn to_text(&self) -> Utf8Bytes {
        json_text(self)
    }
}

/// `value` as JSON text; if it cannot be serialised (never expected: every
/// field serialises), an `error` message whose text is escaped like any
/// other string, so the client still gets valid JSON.
fn json_text<T: Serialize>(value: &T) -> Utf8Bytes {
    serde_json::to_string(value)
        .unwrap_or_else(|e| {
            serde_json::json!({"type": "error", "detail": e.to_string()}).to_string()
        })
        .into()
}

/// The `type` of every message, in the order the OpenAPI document lists
/// them: a drive's status and link, the buses, leases, writes and
/// settings, alarms, the scope, then the session's own.
const ORDER: [&str; 20] = [
    "status",
    "online",
    "offline",
    "freshness",
    "bus-up",
    "bus-down",
    "lease-expired",
    "lease-stop",
    "lease-ended",
    "write",
    "settings-drift",
    "settings-applied",
    "alarm-raised",
    "alarm-cleared",
    "alarm-acknowledged",
    "scope",
    "lagged",
    "subscribed",
    "reply",
    "error",
];

/// One `oneOf` of every message of both kinds, as if they were one enum.
impl PartialSchema for ServerMessage {
    fn schema() -> RefOr<Schema> {
        let mut messages: Vec<RefOr<Schema>> = [DriveMessage::schema(), StreamMessage::schema()]
            .into_iter()
            .flat_map(|schema| match schema {
                RefOr::T(Schema::OneOf(one_of)) => one_of.items,
                other => vec![other],
            })
            .collect();
        messages.sort_by_key(|m| {
            type_of(m)
                .and_then(|t| ORDER.iter().position(|o| *o == t))
                .unwrap_or(usize::MAX)
        });
        let one_of = messages.into_iter().fold(
            OneOfBuilder::new().description(Some("A message the server sends on the stream.")),
            OneOfBuilder::item,
        );
        RefOr::T(Schema::OneOf(one_of.build()))
    }
}

impl ToSchema for ServerMessage {
    fn name() -> Cow<'static, str> {
        Cow::Borrowed("ServerMessage")
    }

    fn schemas(schemas: &mut Vec<(String, RefOr<Schema>)>) {
        DriveMessage::schemas(schemas);
        StreamMessage::schemas(schemas);
    }
}

/// The `type` a message's schema requires (in an `allOf` when the message
/// flattens a view into itself).
fn type_of(message: &RefOr<Schema>) -> Option<&str> {
    match message {
        RefOr::T(Schema::Object(object)) => match object.properties.get("type")? {
            RefOr::T(Schema::Object(tag)) => tag.enum_values.as_ref()?.first()?.as_str(),
            _ => None,
        },
        RefOr::T(Schema::AllOf(all_of)) => all_of.items.iter().find_map(type_of),
        _ => None,
    }
}

/// A decision of the start-up replay of the safety journal, in words.
#[derive(Debug, Clone, PartialEq, Serialize, ToSchema)]
pub struct RestartDecision {
    /// Drive name.
    pub drive: String,
    /// `stop-holder-gone`, `stop-ran-out`, `stop-unfinished`, `brake-again`,
    /// `stop-unknown-state`, `lease-kept`, `brake-holds` or `not-configured`.
    pub decision: String,
    /// Who held the lease concerned, if anyone.
    pub who: Option<String>,
    /// What was done and why.
    pub text: String,
    /// When (RFC 3339, UTC).
    pub at: String,
}

/// Which drives: `"all"`, one name, or a list of names (unit numbers work
/// on a single bus).
#[derive(Debug, Clone, PartialEq, Deserialize, ToSchema)]
#[serde(untagged)]
pub enum DriveSelection {
    /// `"all"` or one drive.
    One(String),
    /// Several drives (`[]`: none).
    Many(Vec<String>),
}

/// A message the client sends.
#[derive(Debug, Clone, PartialEq, Deserialize, ToSchema)]
#[serde(tag = "type", rename_all = "kebab-case", deny_unknown_fields)]
pub enum ClientMessage {
    /// Receive the updates of these drives from now on (replaces the
    /// previous selection); answered with `subscribed`.
    Subscribe {
        /// `"all"`, a drive, or a list of drives.
        drives: DriveSelection,
    },
    /// Run an operation; answered with `reply` carrying the same `id`.
    ///
    /// `op` is a command name (`activate`, `brake`, ... as in
    /// `POST .../commands/{command}`, body `{"force": bool}`), or `mode`,
    /// `setpoint`, `lease-renew`, `lease-release`, `status` (body
    /// `{"fresh": bool}`), `protection`, `speed-ramp`, `position-ramp`,
    /// `inertia`, `rs485-control`, `replacement`, `settings` (a settings
    /// document, with `"dry_run": true` for a dry run) with the body of the
    /// REST route; `scan`,
    /// `set-address`, `scope-arm`, `scope-trigger` and `scope-cancel` take
    /// `bus` instead of `drive`; `alarm-ack` takes neither, its body is
    /// `{"alarm": id}`. A setpoint's lease also ends when this socket
    /// closes.
    Command {
        /// Any JSON value; echoed in the reply.
        id: Value,
        /// The operation.
        op: String,
        /// The drive (name, or unit number on a single bus).
        #[serde(default)]
        drive: Option<String>,
        /// The bus, for `scan`, `set-address` and the `scope-` operations.
        #[serde(default)]
        bus: Option<String>,
        /// The operation's body, as for the REST route.
        #[serde(default)]
        body: Option<Value>,
    },
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn client_messages_parse() {
        let m: ClientMessage =
            serde_json::from_str(r#"{"type":"subscribe","drives":"all"}"#).unwrap();
        assert_eq!(
            m,
            ClientMessage::Subscribe {
                drives: DriveSelection::One("all".into())
            }
        );
        let m: ClientMessage = serde_json::from_str(
            r#"{"type":"command","id":"a7","op":"setpoint","drive":"conveyor","body":{"speed_rpm":100,"lease_ms":500}}"#,
        )
        .unwrap();
        assert!(matches!(m, ClientMessage::Command { ref op, .. } if op == "setpoint"));
        assert!(
            serde_json::from_str::<ClientMessage>(r#"{"type":"subscribe","drives":"all","x":1}"#)
                .is_err()
        );
        assert!(serde_json::from_str::<ClientMessage>(r#"{"type":"dance"}"#).is_err());
    }

    #[test]
    fn every_message_has_its_place_in_the_document() {
        let RefOr::T(Schema::OneOf(one_of)) = ServerMessage::schema() else {
            panic!("the messages are one oneOf");
        };
        let types: Vec<&str> = one_of.items.iter().filter_map(type_of).collect();
        assert_eq!(types, ORDER);
    }

    /// A value whose serialisation fails with quotes in the message.
    struct Unserialisable;

    impl Serialize for Unserialisable {
        fn serialize<S: serde::Serializer>(&self, _: S) -> Result<S::Ok, S::Error> {
            Err(serde::ser::Error::custom("field \"x\" is \\ broken"))
        }
    }

    #[test]
    fn a_message_that_cannot_be_serialised_is_still_valid_json() {
        let text = json_text(&Unserialisable);
        let v: serde_json::Value = serde_json::from_str(text.as_str()).expect("valid JSON");
        assert_eq!(v["type"], "error");
        assert_eq!(v["detail"], "field \"x\" is \\ broken");
    }
}
