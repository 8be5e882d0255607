//! Who holds a serial port: when a port cannot be taken because another
//! program has it (a daemon polling that line, a terminal program, a
//! running `drivegate probe`), the bus and the probe name that program and
//! its pid from what the system tells: the lock on the device
//! (`/proc/locks`), the processes that have it open (`/proc/<pid>/fd`),
//! and a UUCP lock file (`/run/lock/LCK..ttyUSB0`, kept by minicom and
//! friends).
//!
//! What the system does not tell (another user's processes when not root)
//! is not guessed: the words then say how to ask (`fuser`).
//!
//! A leaf: it reads `/proc` and nothing of drivegate, so the bus (a port
//! that does not open) and the probe (a tool on the bus) both use it.

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

/// The other processes that hold `port` (this one left out): those that
/// hold its lock, or, when the system names none, those that have it
/// open.
pub(crate) fn holders(port: &str) -> Vec<Holder> {
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
        // The pid that took a lock may be gone while a child that
        // inherited the descriptor keeps it: that child is found below.
        for pid in lock_holders(&locks, device.dev, device.ino) {
            if Path::new(&format!("/proc/{pid}")).exists() {
                add(pid, true);
            }
        }
    }
    for pid in uucp_lock_holders(&device.path) {
        add(pid, true);
    }
    for pid in open_by(&device) {
        add(pid, false);
    }
    // Who holds the lock is who keeps the port; those that merely have
    // it open (the program serving a pty, a child that inherited the
    // descriptor) are named only when no lock holder is known.
    if found.iter().any(|(_, locks)| *locks) {
        found.retain(|(_, locks)| *locks);
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

/// The holders as a list in words: `minicom -D /dev/ttyUSB0 (pid 812,
/// holds its lock); ...`.
pub(crate) fn named(holders: &[Holder]) -> String {
    holders
        .iter()
        .map(|h| {
            format!(
                "{} (pid {}{})",
                h.command,
                h.pid,
                if h.locks { ", holds its lock" } else { "" }
            )
        })
        .collect::<Vec<_>>()
        .join("; ")
}

/// True when one of them is drivegate itself (a daemon, a probe).
pub(crate) fn is_drivegate(holders: &[Holder]) -> bool {
    holders.iter().any(|h| {
        h.command
            .split_whitespace()
            .next()
            .is_some_and(|c| c.ends_with("drivegate"))
    })
}

/// The session whose controlling terminal `port` is (its leader's pid),
/// when `port` leads to a pseudo-terminal (`/dev/pts/N`, followed through
/// links) that a login session has as its terminal, a shell's: someone's
/// terminal, never a serial line. `None` for anything else: a serial
/// adapter, or a pty no session has (a simulator's, socat's). Read from
/// `/proc/<pid>/stat`, without opening the terminal.
pub(crate) fn session_terminal(port: &str) -> Option<(PathBuf, u32)> {
    let target = std::fs::canonicalize(port).ok()?;
    if !target.starts_with("/dev/pts") {
        return None;
    }
    let rdev = std::fs::metadata(&target).ok()?.rdev();
    let processes = std::fs::read_dir("/proc").ok()?;
    processes
        .flatten()
        .filter_map(|p| std::fs::read_to_string(p.path().join("stat")).ok())
        .find_map(|stat| session_of(&stat, rdev))
        .map(|session| (target, session))
}

/// The session of a process from its `/proc/<pid>/stat`, if its
/// controlling terminal is the device `rdev`.
fn session_of(stat: &str, rdev: u64) -> Option<u32> {
    // "pid (comm) state ppid pgrp session tty_nr ...": comm may hold
    // spaces and parentheses, so the fields are counted after the last ')'.
    let fields: Vec<&str> = stat.rsplit_once(')')?.1.split_whitespace().collect();
    let tty: u64 = fields.get(4)?.parse().ok()?;
    let session: u32 = fields.get(3)?.parse().ok()?;
    (tty != 0 && tty == rdev && session > 0).then_some(session)
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

/// A process's command line, short (the program by its file name, not
/// its path; at most 80 characters), or its name.
pub(crate) fn command_of(pid: u32) -> String {
    let raw = std::fs::read(format!("/proc/{pid}/cmdline")).unwrap_or_default();
    let line = command_line(&raw);
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

/// A `/proc/<pid>/cmdline` (NUL-separated) as one line, the program by
/// its file name.
fn command_line(raw: &[u8]) -> String {
    let mut words = raw
        .split(|&b| b == 0)
        .filter(|a| !a.is_empty())
        .map(|a| String::from_utf8_lossy(a).into_owned());
    let Some(program) = words.next() else {
        return String::new();
    };
    let name = program.rsplit('/').next().unwrap_or(&program).to_string();
    std::iter::once(name)
        .chain(words)
        .collect::<Vec<_>>()
        .join(" ")
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
    fn a_terminal_s_session_is_read_from_proc_stat() {
        // /dev/pts/3 is 136:3.
        let pts3 = nix::sys::stat::makedev(136, 3);
        let shell = "4242 (bash) S 4200 4242 4242 34819 4300 4194560 0 0";
        assert_eq!(session_of(shell, pts3), Some(4242));
        // A name with spaces and parentheses; no terminal; another one.
        let odd = "77 (a (b) c) S 1 77 77 34819 -1 0";
        assert_eq!(session_of(odd, pts3), Some(77));
        assert_eq!(session_of("9 (sim) S 1 9 9 0 -1 0", pts3), None);
        assert_eq!(session_of(shell, nix::sys::stat::makedev(136, 4)), None);
    }

    #[test]
    fn a_command_line_names_its_program_by_file_name() {
        assert_eq!(
            command_line(
                b"/usr/local/bin/drivegate\0serve\0--config\0/etc/drivegate/drivegate.toml\0"
            ),
            "drivegate serve --config /etc/drivegate/drivegate.toml"
        );
        assert_eq!(
            command_line(b"minicom\0-D\0/dev/ttyUSB0\0"),
            "minicom -D /dev/ttyUSB0"
        );
        assert_eq!(command_line(b""), "");
    }

    #[test]
    fn a_port_that_does_not_exist_has_no_holder() {
        assert!(holders("/dev/nonexistent-adapter").is_empty());
    }
}
