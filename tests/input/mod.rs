//! Bad input to every face, over real sockets, while a bystander keeps
//! getting correct answers: generated HTTP requests, schemathesis, slow
//! and hung clients, garbage on the WebSocket and on Modbus TCP. Nothing
//! crashes, nothing leaks, nothing reaches the wire that should not.
//!
//! A new bad-input test goes into the module of its face here.

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod http;
mod modbus_tcp;
mod schemathesis;
mod slow_clients;
mod websocket;
