//! The reloader: applies a changed configuration file without a restart.
//!
//! One task takes reloads one at a time, from `systemctl reload` (SIGHUP,
//! through `crate::daemon`) and from any face (through the control core,
//! which checks the caller's role and audits: `Control::reload`). Each
//! reload reads the file, checks it as `drivegate check-config` would (a
//! file that does not pass leaves everything as it was, and says why with
//! `file:line:column`), compares it with the running configuration
//! (`config::diff`, pure), stops the drives it removes while their bus
//! still runs (`Control::retire`; and the drives of a bus moved to another
//! port: other motors are behind it), has the plant apply each bus's
//! changes (`Plant::apply`: in place between two transactions, the port
//! kept open, unless the port, the baud rate or the transport changed,
//! which reopen that bus alone), tells what the drives of a reopened bus
//! did meanwhile, from their own statuses (`pause`: how long their
//! polling paused, and any whose motion changed, in `stopped`), has the
//! core follow renamed drives (`Control::renamed`), publishes the new
//! configuration, which the
//! faces follow for their own sections (tokens, Modbus TCP clients and
//! units) and the core for `[safety]`, and restarts only the faces whose
//! listener or client section changed (`faces::Running::follow`: a
//! listen address, TLS files, connection limits, `[mqtt]`).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tracing::{info, warn};

use crate::config::Config;
use crate::config::diff::{Changes, diff};
use crate::config::edit::sha256_hex;
use crate::config::file::GENERATIONS;
use crate::control::Control;
use crate::control::reload::{Applied, NewText, Refused, ReloadRequest, ReloadResult};
use crate::daemon::supervisor::Running;
use crate::plant::{Directory, Plant, Rebuild};

mod pause;

/// Reloads waiting for the reloader.
const QUEUE: usize = 8;

/// The reloader of the file at `path`, running `config` now.
pub struct Reloader {
    path: PathBuf,
    running: Arc<Config>,
    plant: Arc<Plant>,
    control: Control,
    faces: Arc<Running>,
}

impl Reloader {
    /// Starts the reloader of `path` (whose text `config` is) and attaches
    /// it to the core; it restarts `faces` as their sections change, and
    /// ends with `shutdown`.
    pub fn start(
        path: &Path,
        config: Arc<Config>,
        plant: Arc<Plant>,
        control: Control,
        faces: Arc<Running>,
        shutdown: CancellationToken,
    ) -> tokio::task::JoinHandle<()> {
        let (tx, rx) = mpsc::channel(QUEUE);
        control.attach_reloader(tx, path);
        let reloader = Reloader {
            path: path.to_path_buf(),
            running: config,
            plant,
            control,
            faces,
        };
        tokio::spawn(reloader.run(rx, shutdown))
    }

    async fn run(
        mut self,
        mut requests: mpsc::Receiver<ReloadRequest>,
        shutdown: CancellationToken,
    ) {
        loop {
            let request = tokio::select! {
                () = shutdown.cancelled() => return,
                request = requests.recv() => match request {
                    Some(r) => r,
                    None => return,
                },
            };
            let result = self.reload(&request.by, request.write).await;
            self.control.record_reload(&result);
            match &result {
                Ok(applied) if applied.problems.is_empty() => info!(
                    by = %request.by,
                    "configuration reloaded from {}: {}",
                    self.path.display(),
                    applied.changes.join("; ")
                ),
                Ok(applied) => warn!(
                    by = %request.by,
                    "configuration reloaded in part from {}: {}; not done: {}",
                    self.path.display(),
                    applied.changes.join("; "),
                    applied.problems.join("; ")
                ),
                Err(refused) => warn!(
                    by = %request.by,
                    "configuration reload refused, the running configuration stays: {refused}"
                ),
            }
            // The one who asked may have gone; the reload stands.
            let _ = request.reply.send(result);
        }
    }

    async fn reload(&mut self, by: &str, write: Option<NewText>) -> ReloadResult {
        let origin = self.path.display().to_string();
        let mut text = std::fs::read_to_string(&self.path)
            .map_err(|e| Refused::Invalid(format!("cannot read {origin}: {e}")))?;
        if let Some(write) = write {
            let on_disk = sha256_hex(&text);
            if on_disk != write.base_sha256 {
                return Err(Refused::Changed(format!(
                    "{origin} changed on disk since it was read (its SHA-256 is now {on_disk}): read it again and redo the change"
                )));
            }
            check(&write.text, &origin)?;
            crate::config::file::replace(&self.path, &write.text, GENERATIONS).map_err(|e| {
                let why = not_written(&origin, &e);
                if read_only(&e) {
                    Refused::NotWritten(why)
                } else {
                    Refused::Invalid(why)
                }
            })?;
            info!(by, "configuration file {origin} rewritten");
            text = write.text;
        }
        let new = check(&text, &origin)?;
        for warning in crate::config::warnings::warnings(&new, &text, &origin) {
            warn!(by, "{warning}");
        }
        let changes = diff(&self.running, &new);
        let first_token = first_token(&self.running, &new);
        let mut applied = self.apply(new, changes).await;
        applied.changes.extend(first_token);
        Ok(applied)
    }

    async fn apply(&mut self, new: Config, mut changes: Changes) -> Applied {
        // The faces say themselves what they did (compared with what each
        // runs with: one that could not follow the last reload tries again).
        changes.faces_restarted.clear();
        let now = self.plant.now();
        // A bus moved to another port has other motors behind it.
        let moved: Vec<String> = changes
            .buses_reopened
            .iter()
            .filter(|(_, why)| why.iter().any(|w| w == "port"))
            .map(|(name, _)| name.clone())
            .collect();
        let reopened: Vec<String> = changes
            .buses_reopened
            .iter()
            .map(|(name, _)| name.clone())
            .filter(|name| !moved.contains(name))
            .collect();
        // Drives that leave, or whose bus moves: stopped while their bus
        // still runs (on its old port).
        let (leaving, moving) = leaving(&now, &new, &moved);
        let on_shutdown = new.safety.on_shutdown;
        let mut stopped = Vec::new();
        if !leaving.is_empty() {
            stopped.extend(self.control.retire(&leaving, on_shutdown).await);
        }
        if !moving.is_empty() {
            let done = self.control.retire(&moving, on_shutdown).await;
            stopped.extend(
                done.into_iter()
                    .map(|line| format!("{line} (its bus moved to another port)")),
            );
        }
        // What the drives of the buses that reopen on their wire do now.
        let before = pause::Before::take(&now, &reopened);
        let rebuild = Rebuild {
            reopen: changes
                .buses_reopened
                .iter()
                .map(|(name, _)| name.clone())
                .collect(),
            moved,
        };
        let problems = self.plant.apply(&new, &rebuild).await;
        let after = self.plant.now();
        for (i, d) in after.indexed_drives() {
            let Some(old) = now.drive_at(i) else { continue };
            // The same motor under a new name: what the core keeps by name
            // follows it.
            if old.name != d.name
                && let Some(bus) = after.bus_at(d.bus)
            {
                self.control.renamed(bus.handle.name(), &old.name, &d.name);
            }
            // A drive whose declared settings changed is compared with them again.
            if d.declared.is_some() && old.declared != d.declared {
                self.control.drift().recheck(i);
            }
        }
        // Polled again after the reopen: how long the polling paused, and
        // whether any drive moves otherwise than before (said by the drive).
        let told = before.after(&after).await;
        stopped.extend(told.stopped);
        let new = Arc::new(new);
        self.control.set_config(new.clone());
        // After the configuration is published: a face started now reads
        // the one it runs with. A listener that moves closes its old socket
        // before this answers, so the old address refuses from then on.
        let faces = self.faces.follow(&new).await;
        self.running = new;
        // `systemctl status` shows the drives and the API's address now.
        crate::daemon::systemd::status(&self.plant, self.faces.addresses().await.http);
        let mut lines = changes.lines();
        if changes.is_empty() && !faces.changes.is_empty() {
            lines.clear();
        }
        lines.extend(faces.changes);
        let mut problems = problems;
        problems.extend(faces.problems);
        Applied {
            changes: lines,
            problems,
            stopped,
            paused: told.paused,
        }
    }
}

/// The drives (slots of `now`) that leave the plant with `new`: those whose
/// bus and unit are no longer configured, and (apart) those on a bus in
/// `moved`, whose port changed.
fn leaving(now: &Directory, new: &Config, moved: &[String]) -> (Vec<usize>, Vec<usize>) {
    let mut leaving = Vec::new();
    let mut moving = Vec::new();
    for (i, d) in now.indexed_drives() {
        let Some(bus) = now.bus_at(d.bus) else {
            leaving.push(i);
            continue;
        };
        let name = bus.handle.name();
        let kept = new
            .buses
            .iter()
            .any(|b| b.name() == name && b.drives.iter().any(|n| n.unit() == d.unit));
        if !kept {
            leaving.push(i);
        } else if moved.iter().any(|m| m == name) {
            moving.push(i);
        }
    }
    (leaving, moving)
}

/// What the first API token changes, when `new` brings it: every client
/// needs a token from now on, loopback included (without tokens, clients
/// on loopback were admin), and how to make an admin token when none has
/// that role. Said in the reload's answer and its log line.
fn first_token(old: &Config, new: &Config) -> Option<String> {
    if !old.http.tokens.is_empty() || new.http.tokens.is_empty() {
        return None;
    }
    let admins: Vec<&str> = new
        .http
        .tokens
        .iter()
        .filter(|t| t.role == crate::control::Role::Admin)
        .map(|t| t.name.as_str())
        .collect();
    let mut line = "first API token: from now on every client needs a token, on this machine \
                    (loopback) too; until now clients on loopback were admin without one, and \
                    the console now asks for a token"
        .to_string();
    if admins.is_empty() {
        line.push_str(
            "; no token has the admin role, so no client has the admin's controls (scans, \
             ramps, saves to flash, reloads from the console or API): make one with \
             `drivegate token new --name NAME --role admin`, add its lines and reload \
             (systemctl reload drivegate needs no token)",
        );
    } else {
        line.push_str(&format!("; admin tokens: {}", admins.join(", ")));
    }
    Some(line)
}

/// The checks of `drivegate check-config`: the file parses and holds
/// together, its certificates load and its tokens resolve.
fn check(text: &str, origin: &str) -> Result<Config, Refused> {
    crate::api::config_check::check(text, origin).map_err(Refused::Invalid)
}

/// Why the file was not written, in words: a file the service may not
/// write is named as such, with what to do instead.
fn not_written(origin: &str, e: &std::io::Error) -> String {
    if read_only(e) {
        format!(
            "cannot write {origin}: {e}: drivegate may not write its configuration file \
             (its unit or the file's permissions keep it read-only: docs/operations.md, \
             \"Changing the configuration\"); nothing was written: add the lines to the file \
             by hand (sudoedit {origin}) and reload (systemctl reload drivegate)"
        )
    } else {
        format!("cannot write {origin}: {e}; nothing was written")
    }
}

/// True when `e` says the service may not write there (the file's or
/// its directory's permissions, a read-only file system).
fn read_only(e: &std::io::Error) -> bool {
    use std::io::ErrorKind;
    matches!(
        e.kind(),
        ErrorKind::PermissionDenied | ErrorKind::ReadOnlyFilesystem
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(tokens: &[(&str, &str)]) -> Config {
        let mut text = String::new();
        for (i, (name, role)) in tokens.iter().enumerate() {
            text.push_str(&format!(
                "[[http.token]]\nname = \"{name}\"\nrole = \"{role}\"\nsha256 = \"{}\"\n",
                format!("{i:x}").repeat(64).get(..64).unwrap_or_default()
            ));
        }
        match Config::parse(&text, "test.toml") {
            Ok(c) => c,
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn the_first_token_is_said_with_how_to_make_an_admin_one() {
        let none = config(&[]);
        let operator = config(&[("scada", "operator")]);
        let line = first_token(&none, &operator).unwrap_or_default();
        assert!(
            line.starts_with("first API token: from now on every client needs a token, on this machine (loopback) too")
                && line.contains("no token has the admin role")
                && line.contains("`drivegate token new --name NAME --role admin`"),
            "{line}"
        );
        let admin = config(&[("scada", "operator"), ("ops", "admin")]);
        let line = first_token(&none, &admin).unwrap_or_default();
        assert!(line.ends_with("; admin tokens: ops"), "{line}");
        // Not the first: nothing to say; none at all: the loopback rule is back.
        assert_eq!(first_token(&operator, &admin), None);
        assert_eq!(first_token(&admin, &none), None);
        assert_eq!(first_token(&none, &none), None);
    }

    #[test]
    fn a_file_the_service_may_not_write_is_said_with_what_to_do() {
        let e = std::io::Error::from(std::io::ErrorKind::ReadOnlyFilesystem);
        let said = not_written("/etc/drivegate/drivegate.toml", &e);
        assert!(
            said.starts_with("cannot write /etc/drivegate/drivegate.toml: read-only")
                && said.contains("drivegate may not write its configuration file")
                && said.contains("sudoedit /etc/drivegate/drivegate.toml"),
            "{said}"
        );
        let e = std::io::Error::from(std::io::ErrorKind::StorageFull);
        let said = not_written("plant.toml", &e);
        assert!(said.ends_with("; nothing was written"), "{said}");
    }
}
