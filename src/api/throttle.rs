//! Slows down token guessing: the core's sign-in rule
//! ([`crate::control::throttle::SignIns`], the same as OPC UA's), with no
//! name (a bearer token names nobody): an address that presents too many
//! unknown tokens in a short time is answered `429` with `Retry-After` for
//! a while.

pub use crate::control::throttle::{Failure, SignIns, key};
