//! Logging through `tracing`: human-readable by default, JSON on request,
//! journald when run by systemd.

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

/// Installs the global subscriber; returns a note to log once it is up
/// (e.g. journald was asked for but is not there).
pub fn init(config: &LogConfig) -> Option<String> {
    let filter = EnvFilter::try_from_default_env()
        .or_else(|_| EnvFilter::try_new(&config.level))
        .unwrap_or_else(|_| EnvFilter::new("info"));
    let registry = tracing_subscriber::registry().with(filter);
    let want_journald = match config.format {
        LogFormat::Journald => true,
        LogFormat::Auto => std::env::var_os("JOURNAL_STREAM").is_some(),
        _ => false,
    };
    let mut note = None;
    if want_journald {
        match tracing_journald::layer() {
            Ok(layer) => {
                let _ = registry
                    .with(layer.with_syslog_identifier("drivegate".into()))
                    .try_init();
                return None;
            }
            Err(e) => {
                note = Some(format!(
                    "journald is not available ({e}); logging to stderr"
                ))
            }
        }
    }
    let result = if config.format == LogFormat::Json {
        registry
            .with(
                tracing_subscriber::fmt::layer()
                    .json()
                    .with_writer(std::io::stderr),
            )
            .try_init()
    } else {
        registry
            .with(tracing_subscriber::fmt::layer().with_writer(std::io::stderr))
            .try_init()
    };
    if result.is_err() {
        note = Some("a logger was already installed".to_string());
    }
    note
}
