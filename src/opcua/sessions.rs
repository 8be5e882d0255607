//! Each OPC UA session is a session of the core: the leases its setpoints
//! and modes take end with `[opcua] comm_loss_action` when it closes or
//! times out (a client that vanished), and across a restart from the
//! safety journal, as for Modbus TCP and MQTT.
//!
//! async-opcua tells no one when a session closes or expires, and its
//! session type cannot be named outside the crate. So the face keeps, for
//! each session that wrote or called a method, a weak reference to the
//! crate's session (in a closure, where its type needs no name) beside
//! the core's [`SessionGuard`], and looks at it every [`CHECK`]: while the
//! session is alive (activated, and a request came within its timeout,
//! the crate's own silence clock) the guard is told it is active; once it
//! is gone, closed or past its timeout, the guard is dropped and its
//! leases end with their stop. The core's communication-loss time is the
//! session's own timeout, so a watcher that stalled cannot keep a lease.
//!
//! A caller is named as every face names a client, by its address: the
//! session's user and the address of the client's connection
//! (`opcua alice (10.0.0.5:50412)` in the audit log), which the vendored
//! crate keeps on the session (`Session::peer_address`, vendor/README.md).
//! A session that moves to a new connection (its client reconnected) is
//! named by the new address from its next request on. The session's number
//! and the client's application URI are in the face's log, beside the name.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use opcua::server::node_manager::RequestContext;
use opcua::types::StatusCode;
use tokio_util::sync::CancellationToken;

use super::outcome::Answer;
use super::users::Identity;
use crate::bus::SourceId;
use crate::config::StopAction;
use crate::control::{Caller, CommLoss, Control, Face, SessionGuard};

/// The name of `context`'s caller, as the audit log and lease views show
/// it: its user and its client's address (see [`who`]).
pub fn who_of(context: &RequestContext, identity: &Identity) -> Arc<str> {
    let (peer, session) = {
        let session = context.session().read();
        (session.peer_address(), session.session_id_numeric())
    };
    who(&identity.user, peer, session).into()
}

/// How a session's caller is named: `alice (10.0.0.5:50412)`, by the
/// client's address as every face names a client; an IPv4 client of a
/// dual-stack listener by its IPv4 address. Without an address (none is
/// known before a session is activated), by the session's number.
pub fn who(user: &str, peer: Option<SocketAddr>, session: u32) -> String {
    match peer {
        Some(peer) => {
            let peer = SocketAddr::new(peer.ip().to_canonical(), peer.port());
            format!("{user} ({peer})")
        }
        None => format!("{user} (session {session})"),
    }
}

/// How often the sessions are looked at.
pub const CHECK: Duration = Duration::from_millis(250);

/// How a core session ends, for its leases' news.
const CLOSING: &str = "its OPC UA session ended";

/// Where an OPC UA session stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum State {
    /// Activated, and heard from within its timeout.
    Alive,
    /// Closed by its client, or expired by the server.
    Closed,
    /// Silent past its timeout.
    TimedOut,
    /// Gone from the server.
    Gone,
}

impl State {
    /// In words, for the log.
    pub fn words(self) -> &'static str {
        match self {
            State::Alive => "alive",
            State::Closed => "closed",
            State::TimedOut => "timed out",
            State::Gone => "gone",
        }
    }
}

type Probe = Box<dyn Fn() -> State + Send + Sync>;

/// One watched session: how to look at it, its core session, its share of
/// the bus queues and what it is called.
struct Watched {
    probe: Probe,
    guard: SessionGuard,
    source: SourceId,
    who: Arc<str>,
}

/// The sessions that hold (or may hold) leases.
pub struct Sessions {
    control: Control,
    action: StopAction,
    longest: Duration,
    watched: Mutex<HashMap<u32, Watched>>,
}

impl Sessions {
    /// The sessions of a face whose leases end with `action`, of sessions
    /// whose timeout is at most `longest`.
    pub fn new(control: Control, action: StopAction, longest: Duration) -> Self {
        Sessions {
            control,
            action,
            longest,
            watched: Mutex::new(HashMap::new()),
        }
    }

    /// The caller of a request of `context`'s session, within its core
    /// session (opened at its first write or call); refused when the
    /// session's user has no role any more.
    pub fn caller(&self, context: &RequestContext, identity: &Identity) -> Result<Caller, Answer> {
        let Some(role) = identity.role else {
            return Err(Answer::new(
                StatusCode::BadUserAccessDenied,
                format!(
                    "\"{}\" is no longer a user of this server (its [[http.token]] was removed): sign in again",
                    identity.user
                ),
            ));
        };
        let id = context.session_id();
        let who = who_of(context, identity);
        let mut watched = self.watched.lock().unwrap_or_else(|p| p.into_inner());
        let entry = watched
            .entry(id)
            .or_insert_with(|| self.watch(context, who.clone()));
        if entry.who != who {
            // Reactivated on a new connection, or by another user.
            tracing::info!(target: "drivegate::opcua", session = id, was = %entry.who, who = %who, "OPC UA session: its caller is now named anew");
            entry.who = who;
        }
        entry.guard.active();
        let caller = Caller::new(Face::OpcUa, entry.who.clone(), role, entry.source);
        Ok(caller.in_session(Face::OpcUa, entry.guard.id()))
    }

    /// Opens the core session of `context`'s session, whose caller is `who`.
    fn watch(&self, context: &RequestContext, who: Arc<str>) -> Watched {
        let (application, timeout) = {
            let session = context.session().read();
            let timeout = session.deadline().saturating_duration_since(Instant::now());
            (
                session
                    .application_description()
                    .application_uri
                    .as_ref()
                    .to_string(),
                timeout,
            )
        };
        // The request just heard restarted the session's clock: what is
        // left of it is the session's timeout.
        let after = timeout
            .max(Duration::from_secs(1))
            .min(self.longest)
            .as_millis();
        let after = Duration::from_millis(u64::try_from(after).unwrap_or(u64::MAX));
        let (guard, _news) = self.control.open_session(
            CLOSING,
            Some(CommLoss {
                after,
                action: self.action,
                face: Face::OpcUa,
            }),
        );
        tracing::info!(
            target: "drivegate::opcua",
            who = %who,
            session = context.session_id(),
            application = %application,
            timeout_ms = after.as_millis() as u64,
            "OPC UA session: its first write or call opened a session of the core"
        );
        let weak = Arc::downgrade(&context.session);
        Watched {
            probe: Box::new(move || match weak.upgrade() {
                None => State::Gone,
                Some(session) => {
                    let session = session.read();
                    if !session.is_activated() {
                        State::Closed
                    } else if session.deadline() < Instant::now() {
                        State::TimedOut
                    } else {
                        State::Alive
                    }
                }
            }),
            guard,
            source: SourceId::new_unique(),
            who,
        }
    }

    /// Looks at every watched session once: the alive ones are active,
    /// the others' core sessions close (their leases end with their stop).
    fn check(&self) {
        let ended: Vec<(u32, Watched, State)> = {
            let mut watched = self.watched.lock().unwrap_or_else(|p| p.into_inner());
            let gone: Vec<(u32, State)> = watched
                .iter()
                .map(|(id, w)| (*id, (w.probe)()))
                .filter(|(_, state)| *state != State::Alive)
                .collect();
            let ended = gone
                .into_iter()
                .filter_map(|(id, state)| watched.remove(&id).map(|w| (id, w, state)))
                .collect();
            for w in watched.values() {
                w.guard.active();
            }
            ended
        };
        for (id, w, state) in ended {
            tracing::info!(target: "drivegate::opcua", who = %w.who, session = id, "OPC UA session {}: its leases end", state.words());
            drop(w.guard);
        }
    }

    /// Sessions watched now.
    pub fn count(&self) -> usize {
        self.watched.lock().unwrap_or_else(|p| p.into_inner()).len()
    }

    /// Looks at the sessions every [`CHECK`] until `stop`; then every
    /// session's leases end, as when a listener of another face closes.
    pub async fn run(self: Arc<Self>, stop: CancellationToken) {
        let mut tick = tokio::time::interval(CHECK);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = tick.tick() => self.check(),
                () = stop.cancelled() => break,
            }
        }
        self.watched
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_caller_is_named_by_its_user_and_its_clients_address() {
        let v4: SocketAddr = "10.0.0.5:50412".parse().unwrap();
        assert_eq!(who("alice", Some(v4), 7), "alice (10.0.0.5:50412)");
        let v6: SocketAddr = "[fd00::5]:4711".parse().unwrap();
        assert_eq!(who("anonymous", Some(v6), 7), "anonymous ([fd00::5]:4711)");
        // An IPv4 client of a listener on [::].
        let mapped: SocketAddr = "[::ffff:10.0.0.5]:50412".parse().unwrap();
        assert_eq!(who("alice", Some(mapped), 7), "alice (10.0.0.5:50412)");
        assert_eq!(who("alice", None, 7), "alice (session 7)");
    }
}
