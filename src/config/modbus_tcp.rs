//! `[modbus_tcp]` section: the listener, its access rules (which networks
//! may connect, and with which role), the unit map and the polled-copy
//! reads.

use std::collections::BTreeSet;
use std::fmt;
use std::net::SocketAddr;
use std::ops::Range;
use std::time::Duration;

use ipnet::IpNet;
use serde::Deserialize;
use serde::de::{self, Deserializer, Visitor};
use toml::Spanned;

pub use super::comm_loss::CommLossConfig;
use super::role::Role;
use super::safety::StopAction;
use super::values::int_in;

/// The Modbus TCP listener.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct ModbusTcpConfig {
    /// Serve Modbus TCP at all.
    pub enabled: bool,
    /// Address and port to listen on (502 in deployment).
    pub listen: SocketAddr,
    /// Connections served at once (each listener, plain and Security);
    /// absent: twice the configured drives plus 32, at least 64
    /// ([`Self::connection_limit`]), so a SCADA with a connection per
    /// drive fits beside the PLCs and HMIs.
    pub max_connections: Option<ConnectionCount>,
    /// A hard cap on the connections one client address (an IPv6 client
    /// by its /64) may hold at once; absent: none, an address shares every
    /// free slot, and near the limit the heaviest address gives way first
    /// (`crate::connections::budget`).
    pub max_connections_per_address: Option<Spanned<ConnectionCount>>,
    /// A connection with nothing pending that sends no complete request for
    /// this long is closed, so dead peers do not hold connection slots.
    #[serde(deserialize_with = "int_in::<_, _, 100, 86_400_000>")]
    pub idle_timeout_ms: u64,
    /// Requests one connection may have waiting for the bus at once; further
    /// pipelined requests wait in the connection's buffer until one is
    /// answered.
    #[serde(deserialize_with = "int_in::<_, _, 1, 64>")]
    pub max_pipelined: usize,
    /// Client networks allowed to connect, with the admin role (viewer
    /// with `read_only`); others are closed at once. Absent: loopback only
    /// ([`Self::allowed`]).
    pub allowed_networks: Option<Vec<IpNet>>,
    /// Client networks allowed to connect with a role of their own (and
    /// the still-check override); the most specific entry a client is in,
    /// here or in `allowed_networks`, decides.
    pub clients: Vec<ClientNetwork>,
    /// Every client is a viewer: every request that could change a drive
    /// is refused (exception 0x01).
    pub read_only: bool,
    /// Answer a broadcast (unit 0) once it is on the wire; off, the client
    /// gets no reply, as Modbus specifies for broadcasts.
    pub broadcast_reply: bool,
    /// Which Modbus TCP unit ids go to which bus and unit; empty: every
    /// configured drive under its own unit number.
    pub unit_map: Vec<UnitMapEntry>,
    /// Buses whose status reads are answered from the latest poll.
    pub polled_copy: Vec<PolledCopy>,
    /// Function codes the control core cannot decode (coils, file records,
    /// diagnostics that restart or clear, vendor codes) that admins may
    /// send, unchecked and audited as such, to one unit (never unit 0);
    /// refused with exception 0x01 for everyone otherwise.
    pub raw_functions: Vec<Spanned<RawFunction>>,
    /// `[modbus_tcp.tls]`: the Modbus/TCP Security listener beside this one.
    pub tls: Option<crate::config::ModbusTlsConfig>,
}

/// A client network and what its clients may do, with its
/// communication-loss function.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ClientNetwork {
    /// The network (CIDR), e.g. "10.1.0.0/16".
    pub network: IpNet,
    /// What its clients may do: `viewer` (reads), `operator` (setpoints,
    /// modes, brake, resets) or `admin` (also protection, ramps, inertia,
    /// saves, calibration, address, factory reset, writes to registers
    /// outside the drive's table, and the codes of `raw_functions`).
    pub role: Spanned<Role>,
    /// Send saves to flash, factory reset, address setting and calibration
    /// even while the motor turns (refused with exception 0x06 otherwise).
    #[serde(default)]
    pub allow_saves_while_moving: bool,
    /// The communication-loss time, ms: a setpoint or mode command from a
    /// client of this network takes a lease on the drive, held by its
    /// connection; any request on the connection renews it; no request for
    /// this long, or the connection closing, ends it with
    /// `comm_loss_action`. Absent: off (no lease, as without the entry).
    #[serde(default, deserialize_with = "comm_loss_ms")]
    pub comm_loss_ms: Option<u64>,
    /// What the end of such a lease sends: `zero-speed` (the default),
    /// `brake`, or `none` (the lease is shown and its end audited and
    /// counted, but nothing is written to the drive).
    #[serde(default)]
    pub comm_loss_action: Option<Spanned<StopAction>>,
}

/// Shortest communication-loss time: below it, a PLC's ordinary jitter
/// would stop the motor.
pub const COMM_LOSS_MIN_MS: u64 = 20;
/// Longest communication-loss time.
pub const COMM_LOSS_MAX_MS: u64 = 60_000;

impl ClientNetwork {
    /// The role of its clients.
    pub fn role(&self) -> Role {
        *self.role.get_ref()
    }

    /// Its communication-loss function, if it has a time.
    pub fn comm_loss(&self) -> Option<CommLossConfig> {
        Some(CommLossConfig {
            after: Duration::from_millis(self.comm_loss_ms?),
            action: self
                .comm_loss_action
                .as_ref()
                .map_or(StopAction::ZeroSpeed, |a| *a.get_ref()),
        })
    }
}

/// `comm_loss_ms`, refused outside its bounds with the key and the range.
fn comm_loss_ms<'de, D: Deserializer<'de>>(d: D) -> Result<Option<u64>, D::Error> {
    let v = i64::deserialize(d)?;
    match u64::try_from(v) {
        Ok(ms) if (COMM_LOSS_MIN_MS..=COMM_LOSS_MAX_MS).contains(&ms) => Ok(Some(ms)),
        _ => Err(de::Error::custom(format!(
            "comm_loss_ms = {v} is out of range: valid {COMM_LOSS_MIN_MS} to {COMM_LOSS_MAX_MS} ms"
        ))),
    }
}

/// A number of connections, 1 to 4096.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(try_from = "i64")]
pub struct ConnectionCount(pub usize);

impl TryFrom<i64> for ConnectionCount {
    type Error = String;

    fn try_from(v: i64) -> Result<Self, String> {
        match usize::try_from(v) {
            Ok(n) if (1..=4096).contains(&n) => Ok(ConnectionCount(n)),
            _ => Err(format!("{v} is out of range: valid 1 to 4096")),
        }
    }
}

/// A Modbus function code listed in `raw_functions`, 1 to 127 (the codes
/// from 0x80 up are exception replies).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(try_from = "i64")]
pub struct RawFunction(u8);

impl RawFunction {
    /// The function code.
    pub fn code(self) -> u8 {
        self.0
    }
}

impl TryFrom<i64> for RawFunction {
    type Error = String;

    fn try_from(v: i64) -> Result<Self, String> {
        match u8::try_from(v) {
            Ok(code @ 1..=127) => Ok(RawFunction(code)),
            _ => Err(format!(
                "function code {v} is out of range: valid 1 to 127 (0x01 to 0x7F; from 0x80 up are exception replies)"
            )),
        }
    }
}

/// One range of the unit map.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct UnitMapEntry {
    /// Modbus TCP unit ids ("101-132" or a single id).
    pub units: Spanned<UnitRange>,
    /// The bus they go to.
    pub bus: Spanned<String>,
    /// The units on that bus, in order (default: the same numbers).
    #[serde(default)]
    pub bus_units: Option<Spanned<UnitRange>>,
}

impl UnitMapEntry {
    /// The Modbus TCP unit ids.
    pub fn units(&self) -> UnitRange {
        *self.units.get_ref()
    }

    /// The name of the bus.
    pub fn bus(&self) -> &str {
        self.bus.get_ref()
    }

    /// The bus unit a Modbus TCP unit of this entry goes to.
    pub fn bus_unit(&self, tcp_unit: u8) -> Option<u8> {
        let units = self.units();
        if !units.contains(tcp_unit) {
            return None;
        }
        let first = self
            .bus_units
            .as_ref()
            .map_or(units, |b| *b.get_ref())
            .first;
        first.checked_add(tcp_unit - units.first)
    }
}

/// Polled-copy reads on one bus.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PolledCopy {
    /// The bus.
    pub bus: Spanned<String>,
    /// Oldest poll a read may be answered from; older goes to the bus.
    #[serde(deserialize_with = "int_in::<_, _, 1, 60_000>")]
    pub max_age_ms: u64,
}

impl PolledCopy {
    /// The maximum age as a duration.
    pub fn max_age(&self) -> Duration {
        Duration::from_millis(self.max_age_ms)
    }
}

/// A range of unit addresses, 1 to 255, written `"101-132"` or `7`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UnitRange {
    /// First unit.
    pub first: u8,
    /// Last unit (inclusive).
    pub last: u8,
}

impl UnitRange {
    /// Number of units in the range.
    pub fn len(&self) -> usize {
        usize::from(self.last - self.first) + 1
    }

    /// Never empty; here for clippy's `len_without_is_empty`.
    pub fn is_empty(&self) -> bool {
        false
    }

    /// True when `unit` is in the range.
    pub fn contains(&self, unit: u8) -> bool {
        (self.first..=self.last).contains(&unit)
    }

    /// True when the two ranges share a unit.
    pub fn overlaps(&self, other: &UnitRange) -> bool {
        self.first <= other.last && other.first <= self.last
    }

    fn from_ints(first: i64, last: i64) -> Result<Self, String> {
        let unit = |v: i64| match u8::try_from(v) {
            Ok(u) if u >= 1 => Ok(u),
            _ => Err(format!(
                "unit {v} is out of range: valid 1 to 255 (0 is the broadcast address, never mapped)"
            )),
        };
        let (first, last) = (unit(first)?, unit(last)?);
        if first > last {
            return Err(format!(
                "unit range {first}-{last} runs backwards: write the lower unit first"
            ));
        }
        Ok(UnitRange { first, last })
    }
}

impl fmt::Display for UnitRange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.first == self.last {
            write!(f, "{}", self.first)
        } else {
            write!(f, "{}-{}", self.first, self.last)
        }
    }
}

impl std::str::FromStr for UnitRange {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        let number = |part: &str| {
            part.trim().parse::<i64>().map_err(|_| {
                format!(
                    "\"{s}\" is not a unit range: write \"first-last\" (e.g. \"1-32\") or one unit"
                )
            })
        };
        match s.split_once('-') {
            Some((a, b)) => UnitRange::from_ints(number(a)?, number(b)?),
            None => {
                let v = number(s)?;
                UnitRange::from_ints(v, v)
            }
        }
    }
}

impl<'de> Deserialize<'de> for UnitRange {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct RangeVisitor;

        impl Visitor<'_> for RangeVisitor {
            type Value = UnitRange;

            fn expecting(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str("a unit (7) or a unit range (\"1-32\")")
            }

            fn visit_i64<E: de::Error>(self, v: i64) -> Result<UnitRange, E> {
                UnitRange::from_ints(v, v).map_err(E::custom)
            }

            fn visit_u64<E: de::Error>(self, v: u64) -> Result<UnitRange, E> {
                let v = i64::try_from(v).unwrap_or(i64::MAX);
                UnitRange::from_ints(v, v).map_err(E::custom)
            }

            fn visit_str<E: de::Error>(self, v: &str) -> Result<UnitRange, E> {
                v.parse().map_err(E::custom)
            }
        }

        d.deserialize_any(RangeVisitor)
    }
}

/// The connection limit of a listener without `max_connections`, with
/// `drives` configured: a connection per drive for a SCADA that models
/// each drive as a device (as Ignition and Kepware do), as many again for
/// a second one or its standby, and 32 for PLCs and HMIs; at least 64.
pub fn default_connection_limit(drives: usize) -> usize {
    drives.saturating_mul(2).saturating_add(32).clamp(64, 4096)
}

/// The networks allowed without `allowed_networks`: loopback only, the
/// gateway's own processes. A plant network is opened with a role of its
/// own (`[[modbus_tcp.clients]]`): plain Modbus TCP has no authentication,
/// so no network gets the admin role by default.
pub fn default_allowed_networks() -> Vec<IpNet> {
    ["127.0.0.0/8", "::1/128"]
        .iter()
        .filter_map(|n| n.parse().ok())
        .collect()
}

/// The networks `allowed_networks` defaulted to before it became loopback
/// only, named in the start-up message of a file that relied on them.
pub const OLD_DEFAULT_NETWORKS: &str =
    "10.0.0.0/8, 172.16.0.0/12, 192.168.0.0/16, 169.254.0.0/16, fc00::/7, fe80::/10";

/// True when every address of `net` is a loopback address.
fn loopback_only(net: &IpNet) -> bool {
    default_allowed_networks().iter().any(|l| l.contains(net))
}

impl Default for ModbusTcpConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            listen: SocketAddr::from(([127, 0, 0, 1], 5020)),
            max_connections: None,
            max_connections_per_address: None,
            idle_timeout_ms: 60_000,
            max_pipelined: 16,
            allowed_networks: None,
            clients: Vec::new(),
            read_only: false,
            broadcast_reply: false,
            unit_map: Vec::new(),
            polled_copy: Vec::new(),
            raw_functions: Vec::new(),
            tls: None,
        }
    }
}

impl ModbusTcpConfig {
    /// The idle timeout as a duration.
    pub fn idle_timeout(&self) -> Duration {
        Duration::from_millis(self.idle_timeout_ms)
    }

    /// The admin networks: `allowed_networks`, or loopback only.
    pub fn allowed(&self) -> Vec<IpNet> {
        self.allowed_networks
            .clone()
            .unwrap_or_else(default_allowed_networks)
    }

    /// Connections served at once with `drives` configured:
    /// `max_connections`, or twice the drives plus 32, at least 64.
    pub fn connection_limit(&self, drives: usize) -> usize {
        self.max_connections
            .map_or_else(|| default_connection_limit(drives), |n| n.0)
    }

    /// The hard cap per address, when configured.
    pub fn per_address_limit(&self) -> Option<usize> {
        self.max_connections_per_address
            .as_ref()
            .map(|n| n.get_ref().0)
    }

    /// What `check-config` and the listener's start say about this section
    /// beyond errors: a non-loopback network with the admin role over
    /// plain Modbus TCP (which has no authentication), and a listener on
    /// the plant network that admits loopback only because
    /// `allowed_networks` is not set (it once defaulted to the private
    /// ranges). Each as `(warning, text)`: a note that is not a warning
    /// describes a configuration that works as written. `listening`: where
    /// the listener is bound (`listen`, or the port the system chose).
    pub fn notices(&self, listening: SocketAddr) -> Vec<(bool, String)> {
        if !self.enabled || listening.ip().is_loopback() {
            return Vec::new();
        }
        let mut out = Vec::new();
        if !self.read_only {
            let admins = self
                .allowed()
                .into_iter()
                .filter(|n| !loopback_only(n))
                .map(|n| (n, "allowed_networks"))
                .chain(
                    self.clients
                        .iter()
                        .filter(|c| c.role() == Role::Admin && !loopback_only(&c.network))
                        .map(|c| (c.network, "[[modbus_tcp.clients]]")),
                );
            for (network, key) in admins {
                out.push((true, format!(
                    "[modbus_tcp] {key} gives {network} the admin role over plain Modbus TCP, which has no authentication: any host there, or one that takes an address there, may save to flash, factory-reset and re-address the drives. Give that network a lesser role with [[modbus_tcp.clients]] (operator or viewer), and commission over Modbus/TCP Security ([modbus_tcp.tls]: client certificates with the role admin; docs/security.md)"
                )));
            }
        }
        if self.allowed_networks.is_none() {
            let clients: Vec<String> = self
                .clients
                .iter()
                .map(|c| format!("{} ({})", c.network, c.role().name()))
                .collect();
            let (warning, admitted) = if clients.is_empty() {
                (true, "loopback only".to_string())
            } else {
                (false, format!("loopback and {}", clients.join(", ")))
            };
            out.push((warning, format!(
                "Modbus TCP listens on {listening} but admits {admitted}; other addresses are refused at connect. [modbus_tcp] allowed_networks is not set, and no longer defaults to the private networks ({OLD_DEFAULT_NETWORKS}) with the admin role. To let a plant network in, give it a role: [[modbus_tcp.clients]] network = \"10.0.5.0/24\" role = \"operator\" (README, Upgrading)"
            )));
        }
        out
    }

    /// Checks against the rest of the configuration: the unit map and the
    /// polled-copy entries must name configured buses, map ranges of equal
    /// length and not overlap; with `read_only`, no client network may
    /// have a role above viewer. An error comes with the span of the value
    /// to fix.
    pub fn validate(&self, config: &crate::config::Config) -> Result<(), (Range<usize>, String)> {
        let bus_names: Vec<&str> = config.buses.iter().map(|b| b.name()).collect();
        self.check_unit_map(&bus_names)?;
        self.check_polled_copy(&bus_names)?;
        self.check_comm_loss()?;
        if let Some(per) = &self.max_connections_per_address
            && let Some(max) = self.max_connections
            && per.get_ref().0 > max.0
        {
            return Err((
                per.span(),
                format!(
                    "[modbus_tcp] max_connections_per_address = {} is out of range: valid 1 to {} (max_connections)",
                    per.get_ref().0,
                    max.0
                ),
            ));
        }
        for raw in &self.raw_functions {
            check_raw(raw)?;
        }
        self.check_read_only()
    }

    /// Each unit map entry names a configured bus, maps ranges of equal
    /// length, and overlaps no entry before it.
    fn check_unit_map(&self, bus_names: &[&str]) -> Result<(), (Range<usize>, String)> {
        for (i, entry) in self.unit_map.iter().enumerate() {
            let units = entry.units();
            let what = format!("unit_map entry {} (units {units})", i + 1);
            known_bus(bus_names, &entry.bus, &what)?;
            if let Some(bus_units) = &entry.bus_units
                && bus_units.get_ref().len() != units.len()
            {
                return Err((
                    bus_units.span(),
                    format!(
                        "[modbus_tcp] {what}: bus_units {} has {} units but units {units} has {}: give ranges of the same length",
                        bus_units.get_ref(),
                        bus_units.get_ref().len(),
                        units.len()
                    ),
                ));
            }
            if let Some((j, other)) = self.unit_map[..i]
                .iter()
                .enumerate()
                .find(|(_, o)| o.units().overlaps(&units))
            {
                return Err((
                    entry.units.span(),
                    format!(
                        "[modbus_tcp] {what} overlaps unit_map entry {} (units {}): each Modbus TCP unit id may go to one place only",
                        j + 1,
                        other.units()
                    ),
                ));
            }
        }
        Ok(())
    }

    /// Each polled-copy entry names a configured bus, each bus once.
    fn check_polled_copy(&self, bus_names: &[&str]) -> Result<(), (Range<usize>, String)> {
        let mut seen = BTreeSet::new();
        for (i, entry) in self.polled_copy.iter().enumerate() {
            known_bus(
                bus_names,
                &entry.bus,
                &format!("polled_copy entry {}", i + 1),
            )?;
            if !seen.insert(entry.bus.get_ref().as_str()) {
                return Err((
                    entry.bus.span(),
                    format!(
                        "[modbus_tcp] polled_copy lists bus \"{}\" twice: give one max_age_ms per bus",
                        entry.bus.get_ref()
                    ),
                ));
            }
        }
        Ok(())
    }

    /// A client's communication-loss action comes with its time.
    fn check_comm_loss(&self) -> Result<(), (Range<usize>, String)> {
        if let Some((client, action)) = self.clients.iter().find_map(|c| {
            Some((c, c.comm_loss_action.as_ref()?)).filter(|_| c.comm_loss_ms.is_none())
        }) {
            return Err((
                action.span(),
                format!(
                    "[modbus_tcp] the clients entry for {} has comm_loss_action but no comm_loss_ms: give the time ({COMM_LOSS_MIN_MS} to {COMM_LOSS_MAX_MS} ms) after which a silent client's motors get the action, or remove comm_loss_action",
                    client.network
                ),
            ));
        }
        Ok(())
    }

    /// With `read_only`, no client network has a role above viewer.
    fn check_read_only(&self) -> Result<(), (Range<usize>, String)> {
        if self.read_only
            && let Some(client) = self.clients.iter().find(|c| c.role() > Role::Viewer)
        {
            return Err((
                client.role.span(),
                format!(
                    "[modbus_tcp] read_only = true makes every client a viewer, but the clients entry for {} gives the role {}: remove read_only, or make the entry a viewer",
                    client.network,
                    client.role().name()
                ),
            ));
        }
        Ok(())
    }
}

/// `bus` (what `what` names) must be one of `bus_names`.
fn known_bus(
    bus_names: &[&str],
    bus: &Spanned<String>,
    what: &str,
) -> Result<(), (Range<usize>, String)> {
    if bus_names.contains(&bus.get_ref().as_str()) {
        Ok(())
    } else {
        Err((
            bus.span(),
            format!(
                "[modbus_tcp] {what} names bus \"{}\", which is not configured (buses: {})",
                bus.get_ref(),
                quoted(bus_names)
            ),
        ))
    }
}

/// A `raw_functions` entry must be a code the control core cannot decode:
/// a read passes anyway, and a register write is always decided by the
/// core, which no list may turn off.
fn check_raw(raw: &Spanned<RawFunction>) -> Result<(), (Range<usize>, String)> {
    use crate::modbus::function::{Effect, effect, name};
    let code = raw.get_ref().code();
    let why = match effect(&[code]) {
        Effect::Other => return Ok(()),
        Effect::Read => "a read, which passes without being listed",
        Effect::RegisterWrite => {
            "a register write, which the control core decodes and always checks (roles, standstill, leases)"
        }
    };
    Err((
        raw.span(),
        format!(
            "[modbus_tcp] raw_functions lists 0x{code:02X} ({}): {why}; list only function codes drivegate cannot decode (e.g. 0x05, 0x0F, 0x15, 0x08, or a vendor's 0x41)",
            name(code)
        ),
    ))
}

fn quoted(names: &[&str]) -> String {
    names
        .iter()
        .map(|n| format!("\"{n}\""))
        .collect::<Vec<_>>()
        .join(", ")
}

#[cfg(test)]
mod tests;
