//! The MQTT face.

pub mod store;
