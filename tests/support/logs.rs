//! The daemon's log, captured. A process has one global subscriber, and
//! the tests of a binary share the process, so there is one capture per
//! binary: a test reads the whole text and picks its own lines by what
//! only its daemon or its clients can have written (a client's address, a
//! token's name, a unique value).

use std::sync::{Arc, Mutex, OnceLock};

/// Everything logged (every level, every target but the test clients'
/// libraries) since the first test of this binary asked for the capture.
#[derive(Clone, Default)]
pub struct Captured(Arc<Mutex<Vec<u8>>>);

impl std::io::Write for Captured {
    fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
        self.0.lock().unwrap().extend_from_slice(bytes);
        Ok(bytes.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        Ok(())
    }
}

impl<'a> tracing_subscriber::fmt::MakeWriter<'a> for Captured {
    type Writer = Captured;

    fn make_writer(&'a self) -> Captured {
        self.clone()
    }
}

/// Installs the capture (once per binary) and returns it; call it before
/// starting the daemon whose lines the test reads. Everything at every
/// level is kept except the events of the test's own clients (their
/// libraries log the requests they send, tokens included, and share this
/// process with the daemon).
pub fn capture_logs() -> &'static Captured {
    use tracing_subscriber::filter::{LevelFilter, Targets};
    use tracing_subscriber::prelude::*;
    static LOGS: OnceLock<Captured> = OnceLock::new();
    LOGS.get_or_init(|| {
        let captured = Captured::default();
        let clients_only = Targets::new()
            .with_default(LevelFilter::TRACE)
            .with_target("tungstenite::handshake::client", LevelFilter::OFF)
            .with_target("reqwest", LevelFilter::OFF)
            .with_target("hyper_util::client", LevelFilter::OFF)
            .with_target("hyper::client", LevelFilter::OFF);
        tracing_subscriber::registry()
            .with(
                tracing_subscriber::fmt::layer()
                    .with_writer(captured.clone())
                    .with_ansi(false),
            )
            .with(clients_only)
            .try_init()
            .expect("no other global subscriber in the tests: use support::logs");
        captured
    })
}

/// The log text so far.
pub fn log_text() -> String {
    String::from_utf8_lossy(&capture_logs().0.lock().unwrap()).into_owned()
}
