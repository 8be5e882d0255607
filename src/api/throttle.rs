//! Slows down token guessing: the core's sign-in throttle
//! ([`crate::control::throttle`]), by address (a bearer token has no
//! name): an address that presents too many unknown tokens in a short time
//! is answered `429` with `Retry-After` for a while.

pub use crate::control::throttle::{Failure, Policy, Throttle, key};
