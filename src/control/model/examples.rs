//! Plain example tests: each bug the model found, as the shrunk case that
//! showed it, replayed through the same world.

use super::run_case;
use super::steps::{Setup, Step};
