//! Logging through `tracing`: human-readable by default, JSON on request,
//! journald when run by systemd.

use std::io::IsTerminal;

use serde::Deserialize;
use tracing_subscriber::EnvFilter;
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;

/// Log output format.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    /// journald when started by systemd (JOURNAL_STREAM set), text otherwise.
    #[default]
    Auto,
    /// One human-readable line per event.
    Text,
    /// One JSON object per line, for log shippers.
    Json,
    /// Straight to the systemd journal, with structured fields.
    Journald,
}

/// `[log]` section.
#[derive(Debug, Clone, Deserialize, PartialEq, Eq)]
#[serde(deny_unknown_fields, default)]
pub struct LogConfig {
    /// Output format.
    pub format: LogFormat,
    /// Filter in `RUST_LOG` syntax, e.g. `info` or `info,drivegate::bus=debug`;
    /// the `RUST_LOG` environment variable overrides it.
    pub level: String,
}

impl Default for LogConfig {
    fn default() -> Self {
        Self {
            format: LogFormat::Auto,
            level: "info".to_string(),
        }
    }
}

/// The OPC UA stack (async-opcua) logs every connection at info and a
/// client's routine mistakes at error: at `[log] level` it says only its
/// warnings, unless the level names one of its targets itself. The face
/// logs what a plant engineer needs (sign-ins refused, certificates
/// rejected, sessions ended) under `drivegate::opcua`.
fn quiet_stacks(level: &str) -> String {
    if level.contains("opcua") {
        return level.to_string();
    }
    format!(
        "{level},opcua_server=warn,opcua_core=warn,opcua_crypto=warn,opcua_nodes=warn,opcua_types=warn"
    )
}

/// Installs the global subscriber; returns notes to log once it is up
/// (journald asked for but not there, a filter that does not parse).
pub fn init(config: &LogConfig) -> Option<String> {
    let mut notes = Vec::new();
    let filter = match std::env::var("RUST_LOG") {
        Ok(env) if !env.trim().is_empty() => EnvFilter::try_new(&env)
            .map_err(|e| {
                notes.push(format!(
                    "RUST_LOG=\"{env}\" is not a valid filter ({e}); using [log] level"
                ))
            })
            .ok(),
        _ => None,
    };
    let filter = filter.unwrap_or_else(|| {
        EnvFilter::try_new(quiet_stacks(&config.level)).unwrap_or_else(|e| {
            notes.push(format!(
                "[log] level = \"{}\" is not a valid filter ({e}); using \"info\"",
                config.level
            ));
            EnvFilter::new("info")
        })
    });
    let registry = tracing_subscriber::registry().with(filter);
    let want_journald = match config.format {
        LogFormat::Journald => true,
        LogFormat::Auto => std::env::var_os("JOURNAL_STREAM").is_some(),
        _ => false,
    };
    if want_journald {
        match tracing_journald::layer() {
            Ok(layer) => {
                let _ = registry
                    .with(layer.with_syslog_identifier("drivegate".into()))
                    .try_init();
                return join(notes);
            }
            Err(e) => notes.push(format!(
                "journald is not available ({e}); logging to stderr"
            )),
        }
    }
    let result = if config.format == LogFormat::Json {
        // Event fields at the top level next to timestamp, level, target and
        // message, as log shippers index them.
        registry
            .with(
                tracing_subscriber::fmt::layer()
                    .json()
                    .flatten_event(true)
                    .with_writer(std::io::stderr),
            )
            .try_init()
    } else {
        // Colours only for a person at a terminal, never into files or pipes.
        registry
            .with(
                tracing_subscriber::fmt::layer()
                    .with_ansi(std::io::stderr().is_terminal())
                    .with_writer(std::io::stderr),
            )
            .try_init()
    };
    if result.is_err() {
        notes.push("a logger was already installed".to_string());
    }
    join(notes)
}

fn join(notes: Vec<String>) -> Option<String> {
    (!notes.is_empty()).then(|| notes.join("; "))
}
