//! What the faces share of the drives' operations, below them all: the
//! problem documents that word a refusal or a failure
//! ([`problem`]), alarms as JSON ([`alarms`]), request bodies' integers ([`integers`]), the status of
//! a drive as JSON ([`status`]), and the translation of the stream's
//! command messages into requests for the control core with the replies
//! they get ([`command_messages`]), and what the daemon hands each face
//! it starts ([`start`]). The REST API and the WebSocket stream use it,
//! and the MQTT face's JSON format: one wording, one shape, whatever the
//! face; the faces do not import each other.

pub(crate) mod alarms;
pub(crate) mod command_messages;
pub(crate) mod integers;
pub(crate) mod messages;
pub(crate) mod problem;
pub(crate) mod start;
pub(crate) mod status;
pub(crate) mod target;
pub(crate) mod writes;
