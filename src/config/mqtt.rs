//! `[mqtt]` section: the MQTT face's broker, its Sparkplug B identity, the
//! role of commands that come over it, and its motor-safety lease. Plain
//! data; `crate::mqtt` reads it. Absent: no MQTT.

use std::fmt;
use std::path::PathBuf;
use std::time::Duration;

use serde::Deserialize;
use serde::de::{self, Deserializer};
use toml::Spanned;

use super::role::Role;
use super::safety::StopAction;
use super::values::int_in;

/// The MQTT face.
#[derive(Debug, Clone, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct MqttConfig {
    /// The broker: `mqtt://host:port` (1883 by default) or
    /// `mqtts://host:port` (TLS, 8883 by default).
    #[serde(deserialize_with = "broker")]
    pub broker: Broker,
    /// What the messages look like: Sparkplug B (the default) or JSON.
    #[serde(default)]
    pub format: Format,
    /// The JSON format's topics start with this (`<prefix>/<drive>/status`
    /// ...); absent: `drivegate/<node_id>`.
    #[serde(default, deserialize_with = "opt_topic_prefix")]
    pub topic_prefix: Option<String>,
    /// The Sparkplug group the node is in.
    #[serde(default = "default_group", deserialize_with = "sparkplug_id")]
    pub group_id: String,
    /// The Sparkplug edge node id (and the MQTT client id's base);
    /// absent: the host's name.
    #[serde(default, deserialize_with = "opt_sparkplug_id")]
    pub node_id: Option<String>,
    /// The Sparkplug primary host: births wait for its `STATE` online, and
    /// its `STATE` offline ends the leases of commands from MQTT.
    #[serde(default, deserialize_with = "opt_sparkplug_id")]
    pub primary_host_id: Option<String>,
    /// The role of commands from MQTT, or `none` (the default): no command
    /// is taken, the face only publishes. Any other needs an authenticated
    /// broker connection (see [`MqttConfig::login`]) or
    /// `unauthenticated_commands`. Read it with [`MqttConfig::commands`].
    #[serde(default)]
    commands: CommandsKey,
    /// Takes commands over a broker connection that is not authenticated
    /// (no user and password, no client certificate): from whoever can
    /// publish on the broker. Warned about by `check-config`, at every
    /// start and at every reload ([`MqttConfig::unauthenticated_warning`]).
    #[serde(default)]
    pub unauthenticated_commands: bool,
    /// The user name given to the broker.
    #[serde(default)]
    pub username: Option<String>,
    /// A file holding the password given to the broker (its first line),
    /// so it is not in the configuration.
    #[serde(default)]
    pub password_file: Option<PathBuf>,
    /// The CA(s), PEM, that signed the broker's certificate (`mqtts://`);
    /// absent: the system's CAs.
    #[serde(default)]
    pub ca: Option<PathBuf>,
    /// A client certificate chain, PEM, for brokers that ask for one
    /// (with `client_key`).
    #[serde(default)]
    pub client_cert: Option<Spanned<PathBuf>>,
    /// Its private key, PEM.
    #[serde(default)]
    pub client_key: Option<PathBuf>,
    /// MQTT keepalive, seconds: a connection cut without a close is
    /// noticed within one and a half of it. At least 5 with the JSON
    /// format (the MQTT 5 client's own floor); read it with
    /// [`MqttConfig::keepalive`].
    #[serde(default = "default_keepalive", deserialize_with = "keepalive")]
    keepalive_s: KeepaliveKey,
    /// The largest message the node takes from the broker, bytes (the
    /// whole MQTT packet: topic, headers and payload). A larger one costs
    /// the message, not the connection: dropped, counted and audited. The
    /// default holds the largest command either format takes with room
    /// to spare (the WebSocket stream's messages are bounded by
    /// `[http] max_body_bytes`, 64 KiB by default).
    #[serde(
        default = "default_max_message_bytes",
        deserialize_with = "int_in::<_, _, 1024, 16_777_216>"
    )]
    pub max_message_bytes: u32,
    /// A setpoint or mode command from MQTT takes a lease held by the MQTT
    /// session; the broker connection lost for this long ends it, ms.
    #[serde(
        default = "default_comm_loss",
        deserialize_with = "int_in::<_, _, 100, 60_000>"
    )]
    pub comm_loss_ms: u64,
    /// What the end of such a lease sends: `zero-speed` (the default),
    /// `brake` or `none`.
    #[serde(default)]
    pub comm_loss_action: StopAction,
    /// Data kept on disk while the broker or the primary host is away, MB
    /// (in `[safety] state_dir`); the oldest goes first.
    #[serde(
        default = "default_store_max_mb",
        deserialize_with = "int_in::<_, _, 0, 65_536>"
    )]
    pub store_max_mb: u64,
    /// Every metric of every drive is published this often, seconds, even
    /// without change; 0: only changes (report by exception).
    #[serde(default, deserialize_with = "int_in::<_, _, 0, 86_400>")]
    pub full_publish_s: u64,
    /// How much a value must change before it is published again.
    #[serde(default)]
    pub deadbands: Deadbands,
}

/// `[mqtt.deadbands]`: a value is published again only once it moved
/// further than this from the value last published. Booleans, the mode,
/// the fault and the turn count are published on every change.
#[derive(Debug, Clone, Copy, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct Deadbands {
    /// Speed, rpm.
    #[serde(deserialize_with = "deadband")]
    pub speed_rpm: f64,
    /// Angle within the turn, degrees.
    #[serde(deserialize_with = "deadband")]
    pub angle_deg: f64,
    /// Motor current, amps.
    #[serde(deserialize_with = "deadband")]
    pub current_a: f64,
    /// Supply voltage, volts.
    #[serde(deserialize_with = "deadband")]
    pub voltage_v: f64,
    /// Temperature, degrees Celsius.
    #[serde(deserialize_with = "deadband")]
    pub temperature_c: f64,
}

impl Default for Deadbands {
    fn default() -> Self {
        Deadbands {
            speed_rpm: 1.0,
            angle_deg: 0.5,
            current_a: 0.05,
            voltage_v: 0.5,
            temperature_c: 1.0,
        }
    }
}

/// The broker's address.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Broker {
    /// TLS (`mqtts://`).
    pub tls: bool,
    /// Host name or address.
    pub host: String,
    /// TCP port.
    pub port: u16,
}

impl fmt::Display for Broker {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let scheme = if self.tls { "mqtts" } else { "mqtt" };
        if self.host.contains(':') {
            write!(f, "{scheme}://[{}]:{}", self.host, self.port)
        } else {
            write!(f, "{scheme}://{}:{}", self.host, self.port)
        }
    }
}

impl Broker {
    /// Parses `mqtt://host[:port]` or `mqtts://host[:port]`.
    pub fn parse(text: &str) -> Result<Broker, String> {
        let (tls, rest) = if let Some(rest) = text.strip_prefix("mqtts://") {
            (true, rest)
        } else if let Some(rest) = text.strip_prefix("mqtt://") {
            (false, rest)
        } else {
            return Err(format!(
                "broker \"{text}\" must start with mqtt:// (plain) or mqtts:// (TLS)"
            ));
        };
        let rest = rest.strip_suffix('/').unwrap_or(rest);
        let default_port = if tls { 8883 } else { 1883 };
        let (host, port) = if let Some(v6) = rest.strip_prefix('[') {
            let (host, after) = v6
                .split_once(']')
                .ok_or_else(|| format!("broker \"{text}\": an IPv6 address needs its ]"))?;
            match after.strip_prefix(':') {
                Some(port) => (host, Some(port)),
                None if after.is_empty() => (host, None),
                None => return Err(format!("broker \"{text}\": expected :port after ]")),
            }
        } else {
            match rest.split_once(':') {
                Some((host, port)) => (host, Some(port)),
                None => (rest, None),
            }
        };
        if host.is_empty() || host.contains(['/', '@', '?', '#', ' ']) {
            return Err(format!(
                "broker \"{text}\": expected mqtt://host:port, e.g. mqtt://127.0.0.1:1883"
            ));
        }
        let port = match port {
            None => default_port,
            Some(p) => match p.parse::<u16>() {
                Ok(p) if p > 0 => p,
                _ => {
                    return Err(format!(
                        "broker \"{text}\": port \"{p}\" is out of range: valid 1 to 65535"
                    ));
                }
            },
        };
        Ok(Broker {
            tls,
            host: host.to_string(),
            port,
        })
    }
}

/// The payload format.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    /// Eclipse Sparkplug B 3.0 (protobuf payloads, births, deaths).
    #[default]
    Sparkplug,
    /// Plain JSON topics for IT tools.
    Json,
}

/// The role of commands from MQTT.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Commands {
    /// Read only: commands are refused, as a viewer's (the core says why).
    #[default]
    None,
    /// The same.
    Viewer,
    /// Setpoints, modes, brake and resets.
    Operator,
    /// Also what needs the admin role.
    Admin,
}

impl Commands {
    /// The role commands have: with none, a viewer's, so the control
    /// core refuses every write in its own words, as it does for any
    /// face's viewer.
    pub fn role(self) -> Role {
        match self {
            Commands::None | Commands::Viewer => Role::Viewer,
            Commands::Operator => Role::Operator,
            Commands::Admin => Role::Admin,
        }
    }
}

/// `commands` with where the file says it (for an error pointing at it);
/// compared and shown by its value only.
#[derive(Clone, Deserialize)]
#[serde(transparent)]
struct CommandsKey(Spanned<Commands>);

impl Default for CommandsKey {
    fn default() -> Self {
        CommandsKey(Spanned::new(0..0, Commands::None))
    }
}

impl PartialEq for CommandsKey {
    fn eq(&self, other: &Self) -> bool {
        self.0.get_ref() == other.0.get_ref()
    }
}

impl fmt::Debug for CommandsKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0.get_ref().fmt(f)
    }
}

/// `keepalive_s` with where the file says it (for the JSON format's
/// floor, checked across keys); compared and shown by its value only.
#[derive(Clone)]
struct KeepaliveKey(Spanned<u64>);

impl PartialEq for KeepaliveKey {
    fn eq(&self, other: &Self) -> bool {
        self.0.get_ref() == other.0.get_ref()
    }
}

impl fmt::Debug for KeepaliveKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.0.get_ref().fmt(f)
    }
}

/// How drivegate logs in to the broker: what the broker knows of the
/// connection its commands arrive on.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Login {
    /// `username` with a `password_file`.
    User(String),
    /// A client certificate over `mqtts://` (`client_cert`, `client_key`).
    Certificate,
    /// Neither: the broker lets anyone in as drivegate does.
    Anonymous,
}

impl MqttConfig {
    /// The role of commands from MQTT (`none`: none are taken).
    pub fn commands(&self) -> Commands {
        *self.commands.0.get_ref()
    }

    /// How drivegate logs in to the broker. A user without a password
    /// file, or a certificate over plain `mqtt://` (where it is not sent),
    /// is no authentication.
    pub fn login(&self) -> Login {
        match (&self.username, &self.password_file) {
            (Some(user), Some(_)) => Login::User(user.clone()),
            _ if self.broker.tls && self.client_cert.is_some() => Login::Certificate,
            _ => Login::Anonymous,
        }
    }

    /// Commands are taken over a connection the broker did not
    /// authenticate (`unauthenticated_commands = true` said so).
    pub fn takes_unauthenticated_commands(&self) -> bool {
        self.commands() != Commands::None && self.login() == Login::Anonymous
    }

    /// Who commands over a connection without a login come from, as the
    /// audit log names them: all that is known is the broker.
    pub fn anonymous_name(&self) -> String {
        format!(
            "unauthenticated broker {}:{}",
            self.broker.host, self.broker.port
        )
    }

    /// What `check-config`, `serve` and every reload say when commands
    /// are taken from any client of the broker: a valid file, on purpose,
    /// but one no stranger should be able to steer.
    pub fn unauthenticated_warning(&self) -> Option<String> {
        self.takes_unauthenticated_commands().then(|| {
            format!(
                "[mqtt] unauthenticated_commands = true: commands are taken from any client of \
                 the broker, which drivegate cannot tell apart (it logs in with no user and no \
                 client certificate); the audit log names them \"{}\". Log in with username \
                 and password_file, or a client certificate over mqtts://, and let the \
                 broker's ACL decide who may command (docs/security.md, MQTT)",
                self.anonymous_name()
            )
        })
    }

    /// Checks across keys: a client certificate comes with its key;
    /// commands come over an authenticated connection only, unless
    /// `unauthenticated_commands` says otherwise.
    pub(super) fn validate(&self) -> Result<(), (std::ops::Range<usize>, String)> {
        if let Some(cert) = &self.client_cert
            && self.client_key.is_none()
        {
            return Err((
                cert.span(),
                "[mqtt] client_cert needs client_key (its private key)".to_string(),
            ));
        }
        if self.client_key.is_some() && self.client_cert.is_none() {
            return Err((0..0, "[mqtt] client_key needs client_cert".to_string()));
        }
        let keepalive = &self.keepalive_s.0;
        if self.format == Format::Json && *keepalive.get_ref() < JSON_KEEPALIVE_MIN_S {
            return Err((
                keepalive.span(),
                format!(
                    "[mqtt] keepalive_s = {} is out of range: valid {JSON_KEEPALIVE_MIN_S} to {KEEPALIVE_MAX_S} with format = \"json\" (the MQTT 5 client's floor; Sparkplug takes {KEEPALIVE_MIN_S})",
                    keepalive.get_ref()
                ),
            ));
        }
        if self.takes_unauthenticated_commands() && !self.unauthenticated_commands {
            return Err((self.commands.0.span(), self.unauthenticated_refusal()));
        }
        Ok(())
    }

    /// Why commands over an unauthenticated connection are refused, and
    /// the ways out.
    fn unauthenticated_refusal(&self) -> String {
        let name = match self.commands() {
            Commands::None => "none",
            Commands::Viewer => "viewer",
            Commands::Operator => "operator",
            Commands::Admin => "admin",
        };
        let certificate_note = if self.client_cert.is_some() && !self.broker.tls {
            " (client_cert is sent over mqtts:// only; the broker is mqtt://)"
        } else {
            ""
        };
        format!(
            "[mqtt] commands = \"{name}\" over a broker connection that is not authenticated{certificate_note}: \
             MQTT does not say who published a command, so only the broker can decide who may \
             (its users and its ACL); a broker that lets drivegate in without credentials lets \
             anyone in. Log in with username and password_file, or with a client certificate \
             (client_cert and client_key) over mqtts://, and let only the SCADA host's user \
             publish commands (docs/security.md, MQTT); or set unauthenticated_commands = true \
             to take commands from any client of the broker (a test bench, a broker only \
             trusted hosts reach)"
        )
    }

    /// The communication-loss time of the MQTT session's leases.
    pub fn comm_loss(&self) -> Duration {
        Duration::from_millis(self.comm_loss_ms)
    }

    /// The keepalive interval.
    pub fn keepalive(&self) -> Duration {
        Duration::from_secs(*self.keepalive_s.0.get_ref())
    }

    /// The largest the store may grow, bytes.
    pub fn store_max_bytes(&self) -> u64 {
        self.store_max_mb.saturating_mul(1024 * 1024)
    }
}

fn default_group() -> String {
    "drivegate".to_string()
}

/// The keepalive's range, seconds (rumqttc's MQTT 3.1.1 client takes
/// any whole second; a keepalive is a 16-bit field).
const KEEPALIVE_MIN_S: u64 = 2;
const KEEPALIVE_MAX_S: u64 = 3600;
/// rumqttc's MQTT 5 client refuses less (it panics: "Keep alives should
/// be >= 5 secs").
const JSON_KEEPALIVE_MIN_S: u64 = 5;

fn default_keepalive() -> KeepaliveKey {
    KeepaliveKey(Spanned::new(0..0, 10))
}

fn keepalive<'de, D: Deserializer<'de>>(d: D) -> Result<KeepaliveKey, D::Error> {
    let v = Spanned::<i64>::deserialize(d)?;
    let span = v.span();
    let v = *v.get_ref();
    match u64::try_from(v) {
        Ok(s) if (KEEPALIVE_MIN_S..=KEEPALIVE_MAX_S).contains(&s) => {
            Ok(KeepaliveKey(Spanned::new(span, s)))
        }
        _ => Err(de::Error::custom(format!(
            "{v} is out of range: valid {KEEPALIVE_MIN_S} to {KEEPALIVE_MAX_S} ({JSON_KEEPALIVE_MIN_S} to {KEEPALIVE_MAX_S} with format = \"json\")"
        ))),
    }
}

fn default_max_message_bytes() -> u32 {
    65_536
}

fn default_comm_loss() -> u64 {
    5000
}

fn default_store_max_mb() -> u64 {
    64
}

fn broker<'de, D: Deserializer<'de>>(d: D) -> Result<Broker, D::Error> {
    let text = String::deserialize(d)?;
    Broker::parse(&text).map_err(de::Error::custom)
}

/// A Sparkplug id: not empty, none of `/ + #` (topic levels and wildcards).
pub fn check_sparkplug_id(id: &str) -> Result<(), String> {
    if id.is_empty() {
        return Err("a Sparkplug id cannot be empty".to_string());
    }
    if let Some(c) = id
        .chars()
        .find(|c| matches!(c, '/' | '+' | '#') || c.is_control())
    {
        return Err(format!(
            "\"{id}\" cannot be a Sparkplug id: it contains '{}' (no /, + or # in a topic level)",
            c.escape_default()
        ));
    }
    Ok(())
}

fn sparkplug_id<'de, D: Deserializer<'de>>(d: D) -> Result<String, D::Error> {
    let id = String::deserialize(d)?;
    check_sparkplug_id(&id).map_err(de::Error::custom)?;
    Ok(id)
}

fn opt_sparkplug_id<'de, D: Deserializer<'de>>(d: D) -> Result<Option<String>, D::Error> {
    sparkplug_id(d).map(Some)
}

/// A topic prefix: topic levels without wildcards, not empty, no empty
/// level (so `<prefix>/<drive>/command` subscribes exactly).
pub fn check_topic_prefix(prefix: &str) -> Result<(), String> {
    if prefix.is_empty() {
        return Err("topic_prefix cannot be empty".to_string());
    }
    if let Some(c) = prefix
        .chars()
        .find(|c| matches!(c, '+' | '#') || c.is_control())
    {
        return Err(format!(
            "topic_prefix \"{prefix}\" contains '{}': no wildcard (+, #) in a topic",
            c.escape_default()
        ));
    }
    if prefix.split('/').any(str::is_empty) {
        return Err(format!(
            "topic_prefix \"{prefix}\" has an empty level: no leading, trailing or double /"
        ));
    }
    Ok(())
}

fn opt_topic_prefix<'de, D: Deserializer<'de>>(d: D) -> Result<Option<String>, D::Error> {
    let prefix = String::deserialize(d)?;
    check_topic_prefix(&prefix).map_err(de::Error::custom)?;
    Ok(Some(prefix))
}

fn deadband<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
    let v = f64::deserialize(d)?;
    if !(v.is_finite() && (0.0..=10_000.0).contains(&v)) {
        return Err(de::Error::custom(format!(
            "deadband {v} is out of range: valid 0 to 10000"
        )));
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topic_prefixes() {
        assert!(check_topic_prefix("drivegate/gw1").is_ok());
        assert!(check_topic_prefix("plant").is_ok());
        for bad in ["", "a/+/b", "a/#", "/a", "a/", "a//b"] {
            assert!(check_topic_prefix(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn brokers() {
        let b = Broker::parse("mqtt://127.0.0.1:1883").unwrap();
        assert_eq!((b.tls, b.host.as_str(), b.port), (false, "127.0.0.1", 1883));
        let b = Broker::parse("mqtts://broker.plant").unwrap();
        assert_eq!((b.tls, b.port), (true, 8883));
        let b = Broker::parse("mqtt://[::1]:1999").unwrap();
        assert_eq!((b.host.as_str(), b.port), ("::1", 1999));
        assert_eq!(b.to_string(), "mqtt://[::1]:1999");
        assert!(Broker::parse("tcp://x:1").unwrap_err().contains("mqtt://"));
        assert!(
            Broker::parse("mqtt://x:70000")
                .unwrap_err()
                .contains("valid 1 to 65535")
        );
        assert!(Broker::parse("mqtt://:1").is_err());
    }

    fn parse(keys: &str) -> Result<MqttConfig, String> {
        let toml = format!("[mqtt]\n{keys}\n");
        crate::config::Config::parse(&toml, "drivegate.toml")
            .map(|c| c.mqtt.unwrap())
            .map_err(|e| e.to_string())
    }

    #[test]
    fn commands_need_an_authenticated_broker_connection() {
        let plain = "broker = \"mqtt://127.0.0.1\"";
        let refused = parse(&format!("{plain}\ncommands = \"operator\"")).unwrap_err();
        for words in [
            "drivegate.toml:3",
            "not authenticated",
            "username and password_file",
            "client certificate",
            "mqtts://",
            "unauthenticated_commands = true",
        ] {
            assert!(refused.contains(words), "{words:?} in {refused}");
        }
        // A certificate over plain MQTT is not sent.
        let refused = parse(&format!(
            "{plain}\ncommands = \"admin\"\nclient_cert = \"a.pem\"\nclient_key = \"a.key\""
        ))
        .unwrap_err();
        assert!(refused.contains("over mqtts:// only"), "{refused}");
        // A user without a password is no login.
        assert!(
            parse(&format!(
                "{plain}\ncommands = \"viewer\"\nusername = \"gw1\""
            ))
            .is_err()
        );
        // The two ways, and the explicit choice.
        let user = parse(&format!(
            "{plain}\ncommands = \"operator\"\nusername = \"gw1\"\npassword_file = \"/p\""
        ))
        .unwrap();
        assert_eq!(user.login(), Login::User("gw1".into()));
        assert!(!user.takes_unauthenticated_commands());
        let cert = parse(
            "broker = \"mqtts://broker\"\ncommands = \"operator\"\nclient_cert = \"a.pem\"\nclient_key = \"a.key\"",
        )
        .unwrap();
        assert_eq!(cert.login(), Login::Certificate);
        let open = parse(&format!(
            "{plain}\ncommands = \"operator\"\nunauthenticated_commands = true"
        ))
        .unwrap();
        assert!(open.takes_unauthenticated_commands());
        // Without commands nothing is asked.
        assert_eq!(parse(plain).unwrap().commands(), Commands::None);
    }

    #[test]
    fn the_keepalive_and_the_largest_message_are_within_the_clients_limits() {
        let broker = "broker = \"mqtt://127.0.0.1\"";
        // rumqttc's MQTT 5 client panics below 5 s: refused at the line.
        let e = parse(&format!("{broker}\nformat = \"json\"\nkeepalive_s = 4")).unwrap_err();
        assert!(e.starts_with("drivegate.toml:4:"), "{e}");
        assert!(e.contains("valid 5 to 3600"), "{e}");
        assert!(parse(&format!("{broker}\nformat = \"json\"\nkeepalive_s = 5")).is_ok());
        // Sparkplug's MQTT 3.1.1 client takes 2.
        let c = parse(&format!("{broker}\nkeepalive_s = 2")).unwrap();
        assert_eq!(c.keepalive(), Duration::from_secs(2));
        let e = parse(&format!("{broker}\nkeepalive_s = 1")).unwrap_err();
        assert!(e.starts_with("drivegate.toml:3:"), "{e}");
        assert!(e.contains("valid 2 to 3600"), "{e}");
        assert_eq!(parse(broker).unwrap().max_message_bytes, 65_536);
        let e = parse(&format!("{broker}\nmax_message_bytes = 1023")).unwrap_err();
        assert!(e.contains("valid 1024 to 16777216"), "{e}");
    }

    #[test]
    fn sparkplug_ids() {
        assert!(check_sparkplug_id("gw-1.plant").is_ok());
        assert!(check_sparkplug_id("a/b").unwrap_err().contains("'/'"));
        assert!(check_sparkplug_id("a+").is_err());
        assert!(check_sparkplug_id("").is_err());
    }
}
