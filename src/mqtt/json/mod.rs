//! The MQTT face's JSON format (`[mqtt] format = "json"`), for IT tools
//! and Node-RED: plain JSON on topics under `topic_prefix`, over MQTT 5
//! (rumqttc's `v5`), so that a command's reply can go to its response
//! topic with its correlation data.
//!
//! - [`topics`] names the topics and reads a command's drive (pure),
//! - `connection` is one MQTT 5 connection with `offline` as its will,
//! - `node` is the task: state, statuses, events, commands and replies,
//!   and the session's motor-safety lease.
//!
//! The messages are the other faces': a drive's status is the API's
//! status JSON, commands are the WebSocket stream's command messages,
//! replies and events the stream's, refusals the API's problem documents
//! (all from [`crate::faces_shared`]).

mod connection;
pub(super) mod node;
pub mod topics;
