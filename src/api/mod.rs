//! The REST + WebSocket face (`/api/v1`), with its OpenAPI document.

pub mod config;
