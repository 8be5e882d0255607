//! Who may connect, and with which role, as the running configuration
//! says: the core's network table ([`crate::control::networks`]), asked
//! on each accept so that a reload applies to the next client.

use std::sync::Arc;

use crate::config::Config;
use crate::control::identity::{Credential, identify};
use crate::control::networks::Networks;

pub use crate::control::networks::Rights;

/// A listener's access, which follows the running configuration: clients
/// that connect after a reload get its networks and roles.
#[derive(Clone)]
pub struct SharedAccess {
    config: Arc<std::sync::RwLock<Arc<Config>>>,
    follower: Arc<crate::control::reload::ConfigFollower>,
}

impl std::fmt::Debug for SharedAccess {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SharedAccess").finish_non_exhaustive()
    }
}

impl SharedAccess {
    /// `config`'s networks until a reload of `control`'s configuration
    /// replaces it.
    pub fn new(config: Arc<Config>, control: &crate::control::Control) -> Self {
        SharedAccess {
            config: Arc::new(std::sync::RwLock::new(config)),
            follower: Arc::new(crate::control::reload::ConfigFollower::new(control)),
        }
    }

    /// What a client from `ip` may do, if it may connect at all: its role
    /// from the core ([`identify`]), the rest from its network's entry.
    pub fn rights(&self, ip: std::net::IpAddr) -> Option<Rights> {
        if let Some(config) = self.follower.changed() {
            *self.config.write().unwrap_or_else(|p| p.into_inner()) = config;
        }
        let config = self
            .config
            .read()
            .unwrap_or_else(|p| p.into_inner())
            .clone();
        let identity = identify(
            &config,
            crate::control::Face::ModbusTcp,
            Credential::Network(ip),
        )
        .ok()?;
        let terms = Networks::from_config(&config.modbus_tcp).rights(ip)?;
        Some(Rights {
            role: identity.role,
            ..terms
        })
    }
}
