//! The primary host application's `STATE` (Sparkplug 3.0, section 7.4):
//! a retained JSON `{"online": bool, "timestamp": ms}` on
//! `spBv1.0/STATE/<host_id>`. Births wait for it to say online, and its
//! offline ends the leases of commands from MQTT. Pure: no I/O.

use serde::Deserialize;

/// A `STATE` message.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
pub struct HostState {
    /// The host is online.
    pub online: bool,
    /// When the host said so, ms since the Unix epoch.
    pub timestamp: u64,
}

impl HostState {
    /// Reads a `STATE` payload; `None` for anything else (a host of
    /// Sparkplug 2.2 sent the plain words `ONLINE`/`OFFLINE`, which 3.0
    /// replaced: they are taken as such, with timestamp 0).
    pub fn parse(payload: &[u8]) -> Option<HostState> {
        match payload {
            b"ONLINE" => Some(HostState {
                online: true,
                timestamp: 0,
            }),
            b"OFFLINE" => Some(HostState {
                online: false,
                timestamp: 0,
            }),
            _ => serde_json::from_slice(payload).ok(),
        }
    }
}

/// What the node knows of its primary host.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Host {
    last: Option<HostState>,
}

/// What a `STATE` message changed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HostChange {
    /// The host came online (or is heard online for the first time).
    Online,
    /// The host went offline.
    Offline,
    /// Nothing: the same state again, or an older message than the last
    /// one taken (spec 3.0: a STATE with an older timestamp is ignored).
    None,
}

impl Host {
    /// The host's state, if heard.
    pub fn online(&self) -> Option<bool> {
        self.last.map(|s| s.online)
    }

    /// Takes a `STATE` message.
    pub fn update(&mut self, state: HostState) -> HostChange {
        if let Some(last) = self.last
            && state.timestamp < last.timestamp
        {
            return HostChange::None;
        }
        let was = self.online();
        self.last = Some(state);
        match (was, state.online) {
            (Some(true), true) | (Some(false) | None, false) => HostChange::None,
            (_, true) => HostChange::Online,
            (Some(true), false) => HostChange::Offline,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state(online: bool, timestamp: u64) -> HostState {
        HostState { online, timestamp }
    }

    #[test]
    fn payloads() {
        assert_eq!(
            HostState::parse(br#"{"online":true,"timestamp":1700000000000}"#),
            Some(state(true, 1_700_000_000_000))
        );
        assert_eq!(HostState::parse(b"OFFLINE"), Some(state(false, 0)));
        assert_eq!(HostState::parse(b"{\"online\":1}"), None);
        assert_eq!(HostState::parse(b"\xff"), None);
    }

    #[test]
    fn online_offline_and_stale_messages() {
        let mut host = Host::default();
        assert_eq!(host.online(), None);
        assert_eq!(host.update(state(false, 5)), HostChange::None);
        assert_eq!(host.update(state(true, 10)), HostChange::Online);
        assert_eq!(host.update(state(true, 11)), HostChange::None);
        // An older offline (a retained message from before) is ignored.
        assert_eq!(host.update(state(false, 9)), HostChange::None);
        assert_eq!(host.online(), Some(true));
        assert_eq!(host.update(state(false, 12)), HostChange::Offline);
        assert_eq!(host.update(state(true, 13)), HostChange::Online);
    }
}
