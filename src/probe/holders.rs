//! Who holds a serial port: when the probe cannot take a port because
//! another program has it (the daemon polling that line, a terminal
//! program, a second probe), it names that program and its pid from what
//! the system tells: the lock on the device (`/proc/locks`), the
//! processes that have it open (`/proc/<pid>/fd`), and a UUCP lock file
//! (`/run/lock/LCK..ttyUSB0`, kept by minicom and friends).
//!
//! What the system does not tell (another user's processes when not root)
//! is not guessed: the message then says how to ask (`fuser`).

use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};

/// A process that holds the port.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Holder {
    /// Its process id.
    pub pid: u32,
    /// Its command line (or its name, when the line cannot be read).
    pub command: String,
    /// True when it holds the port's lock (it opened it exclusively),
    /// false when it only has it open.
    pub locks: bool,
}

/// The device behind `path` (a `/dev/serial/by-id/` link is followed).
struct Device {
    /// The device node's file system and inode (what `/proc/locks` names).
    dev: u64,
    ino: u64,
    /// The character device's number (what an open file of it has too).
    rdev: u64,
    /// Its path, for messages and lock file names.
    path: PathBuf,
}

/// The other processes that hold `port` (this one left out), those that
/// hold its lock first.
pub fn holders(port: &str) -> Vec<Holder> {
    let Ok(meta) = std::fs::metadata(port) else {
        return Vec::new();
    };
    let device = Device {
        dev: meta.dev(),
        ino: meta.ino(),
        rdev: meta.rdev(),
        path: std::fs::canonicalize(port).unwrap_or_else(|_| PathBuf::from(port)),
    };
    let own = std::process::id();
    let mut found: Vec<(u32, bool)> = Vec::new();
    let mut add = |pid: u32, locks: bool| {
        if pid == own {
            return;
        }
        match found.iter_mut().find(|(p, _)| *p == pid) {
            Some(entry) => entry.1 |= locks,
            None => found.push((pid, locks)),
        }
    };
    if let Ok(locks) = std::fs::read_to_string("/proc/locks") {
        for pid in lock_holders(&locks, device.dev, device.ino) {
            add(pid, true);
        }
    }
    for pid in uucp_lock_holders(&device.path) {
        add(pid, true);
    }
    for pid in open_by(&device) {
        add(pid, false);
    }
    found.sort_by_key(|(pid, locks)| (!locks, *pid));
    found
        .into_iter()
        .map(|(pid, locks)| Holder {
            pid,
            command: command_of(pid),
            locks,
        })
        .collect()
}

/// What `probe` says when `port` is held by another program: who, and
/// what to do.
pub fn in_use(port: &str) -> String {
    let holders = holders(port);
    if holders.is_empty() {
        return format!(
            "{port} is in use by another program, which holds it exclusively (the system does \
             not say which to this user: `sudo fuser -v {port}` names it). Stop it, or stop \
             drivegate if it polls this line (sudo systemctl stop drivegate), then probe again"
        );
    }
    let named: Vec<String> = holders
        .iter()
        .map(|h| {
            format!(
                "{} (pid {}{})",
                h.command,
                h.pid,
                if h.locks { ", holds its lock" } else { "" }
            )
        })
        .collect();
    let drivegate = holders.iter().any(|h| {
        h.command
            .split_whitespace()
            .next()
            .is_some_and(|c| c.ends_with("drivegate"))
    });
    let stop = if drivegate {
        "A drivegate daemon polls this line: stop it first (sudo systemctl stop drivegate), \
         or probe from the console's commissioning page, which scans through the daemon"
    } else {
        "Stop it first"
    };
    let who = if holders.len() == 1 {
        "another program"
    } else {
        "other programs"
    };
    format!(
        "{port} is in use by {who}: {}. {stop}, then probe again",
        named.join("; ")
    )
}

/// Pids holding a lock on the file `dev`/`ino` in `/proc/locks`' text.
fn lock_holders(locks: &str, dev: u64, ino: u64) -> Vec<u32> {
    let wanted = format!(
        "{:02x}:{:02x}:{ino}",
        nix::sys::stat::major(dev),
        nix::sys::stat::minor(dev)
    );
    locks
        .lines()
        // "1: FLOCK  ADVISORY  WRITE 812 00:05:3 0 EOF"; a waiter's line
        // has "->" after the number, and holds nothing yet.
        .filter(|l| !l.contains("->"))
        .filter_map(|l| {
            let fields: Vec<&str> = l.split_whitespace().collect();
            (fields.get(5) == Some(&wanted.as_str()))
                .then(|| fields.get(4)?.parse().ok())
                .flatten()
        })
        .collect()
}

/// Pids of the live processes named by a UUCP lock file of the device.
fn uucp_lock_holders(device: &Path) -> Vec<u32> {
    let Some(name) = device.file_name().and_then(|n| n.to_str()) else {
        return Vec::new();
    };
    ["/run/lock", "/var/lock"]
        .iter()
        .filter_map(|dir| std::fs::read(Path::new(dir).join(format!("LCK..{name}"))).ok())
        .filter_map(|bytes| lock_file_pid(&bytes))
        .filter(|pid| Path::new(&format!("/proc/{pid}")).exists())
        .collect()
}

/// The pid a UUCP lock file holds: ten ASCII digits (and a newline), or,
/// the old way, a native 4-byte integer.
fn lock_file_pid(bytes: &[u8]) -> Option<u32> {
    let text = std::str::from_utf8(bytes).ok().map(str::trim);
    if let Some(pid) = text.and_then(|t| t.parse().ok()) {
        return Some(pid);
    }
    let raw: [u8; 4] = bytes.get(..4)?.try_into().ok()?;
    Some(u32::from_ne_bytes(raw)).filter(|&p| p > 0)
}

/// Pids of the processes with the device open (those this user may look
/// at).
fn open_by(device: &Device) -> Vec<u32> {
    let Ok(processes) = std::fs::read_dir("/proc") else {
        return Vec::new();
    };
    let mut pids = Vec::new();
    for process in processes.flatten() {
        let Some(pid) = process.file_name().to_str().and_then(|p| p.parse().ok()) else {
            continue;
        };
        let Ok(fds) = std::fs::read_dir(process.path().join("fd")) else {
            continue;
        };
        let holds = fds.flatten().any(|fd| {
            std::fs::metadata(fd.path()).is_ok_and(|m| {
                (m.rdev() == device.rdev && device.rdev != 0)
                    || (m.dev() == device.dev && m.ino() == device.ino)
            })
        });
        if holds {
            pids.push(pid);
        }
    }
    pids
}

/// A process's command line, short, or its name.
fn command_of(pid: u32) -> String {
    let line = std::fs::read(format!("/proc/{pid}/cmdline"))
        .map(|raw| {
            raw.split(|&b| b == 0)
                .filter(|a| !a.is_empty())
                .map(|a| String::from_utf8_lossy(a).into_owned())
                .collect::<Vec<_>>()
                .join(" ")
        })
        .unwrap_or_default();
    let line = if line.is_empty() {
        std::fs::read_to_string(format!("/proc/{pid}/comm"))
            .map(|c| c.trim().to_string())
            .unwrap_or_else(|_| "a process".to_string())
    } else {
        line
    };
    if line.chars().count() > 80 {
        format!("{}...", line.chars().take(77).collect::<String>())
    } else {
        line
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_lock_holder_is_read_from_proc_locks() {
        let dev = nix::sys::stat::makedev(0, 0x19);
        let text = "1: FLOCK  ADVISORY  WRITE 812 00:19:3 0 EOF\n\
                    1: -> FLOCK  ADVISORY  WRITE 900 00:19:3 0 EOF\n\
                    2: POSIX  ADVISORY  WRITE 77 fe:00:3 0 EOF\n\
                    3: FLOCK  ADVISORY  WRITE 13 00:19:4 0 EOF\n";
        assert_eq!(lock_holders(text, dev, 3), vec![812]);
    }

    #[test]
    fn uucp_lock_files_in_both_forms() {
        assert_eq!(lock_file_pid(b"      4242\n"), Some(4242));
        assert_eq!(lock_file_pid(&4242u32.to_ne_bytes()), Some(4242));
        assert_eq!(lock_file_pid(b""), None);
    }

    #[test]
    fn a_port_that_does_not_exist_has_no_holder() {
        assert!(holders("/dev/nonexistent-adapter").is_empty());
    }
}
