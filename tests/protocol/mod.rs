//! The pure protocol code, without I/O: the maker's golden frames, property
//! tests of encoders and decoders, and the committed fuzz corpus replayed.
//!
//! A new test of `drive/` or `modbus/` that needs no daemon goes here (or,
//! better, beside the code as a unit test).

#![allow(clippy::unwrap_used, clippy::expect_used, unreachable_pub)]

mod fuzz_corpus;
mod listed;
mod properties;
mod sparkplug_proto;
mod vectors;
