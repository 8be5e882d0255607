//! The configuration file on disk, as the console and the API change it:
//! replaced whole or not at all, with its previous versions kept beside
//! it, each with the owner and mode of the file it was.
//!
//! A change is written to a temporary file in the same directory (so the
//! rename cannot cross file systems), with the original's mode and owner,
//! synced, then renamed over the file, and the directory synced: a power
//! cut leaves the old file or the new one, never half of one. Before the
//! rename, the file as it was becomes `<name>.1` (a hard link: the same
//! inode, so its owner, mode and time stay), `<name>.1` becomes `<name>.2`,
//! and so on; the oldest past [`GENERATIONS`] is dropped.

use std::io::Write;
use std::os::unix::fs::{MetadataExt, OpenOptionsExt, PermissionsExt};
use std::path::{Path, PathBuf};
use std::time::SystemTime;

use super::edit::sha256_hex;

/// Previous versions kept beside the file.
pub const GENERATIONS: usize = 5;

/// A previous version of the file.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Generation {
    /// 1 for the newest.
    pub number: usize,
    /// Its path (`<file>.<number>`).
    pub path: PathBuf,
    /// When it was the file (its modification time).
    pub modified: Option<SystemTime>,
}

/// Where generation `number` of `path` is kept.
pub fn generation_path(path: &Path, number: usize) -> PathBuf {
    let mut name = path.as_os_str().to_owned();
    name.push(format!(".{number}"));
    PathBuf::from(name)
}

/// The previous versions of `path` kept now, newest first.
pub fn generations(path: &Path) -> Vec<Generation> {
    (1..=GENERATIONS)
        .filter_map(|number| {
            let at = generation_path(path, number);
            let meta = std::fs::metadata(&at).ok()?;
            Some(Generation {
                number,
                path: at,
                modified: meta.modified().ok(),
            })
        })
        .collect()
}

/// The text of the file or of a previous version of it whose SHA-256
/// (hex) is `sha256`, if one is kept.
pub fn version_with_sha(path: &Path, sha256: &str) -> Option<String> {
    std::iter::once(path.to_path_buf())
        .chain(generations(path).into_iter().map(|g| g.path))
        .filter_map(|p| std::fs::read_to_string(p).ok())
        .find(|text| sha256_hex(text) == sha256)
}

/// Whether drivegate may replace `path`: it may create a file in its
/// directory and write the file (a read-only file system, a directory the
/// service may not write, an immutable file). The error says which.
pub fn may_write(path: &Path) -> std::io::Result<()> {
    use nix::unistd::{AccessFlags, access};
    let dir = directory(path);
    for p in [dir, path] {
        access(p, AccessFlags::W_OK).map_err(|e| {
            std::io::Error::new(
                std::io::Error::from(e).kind(),
                format!("{}: {}", p.display(), e.desc()),
            )
        })?;
    }
    Ok(())
}

fn directory(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// Replaces `path` with `text` whole or not at all, keeping `keep`
/// previous versions; the new file gets the old one's mode and, as far as
/// the system lets this process, its owner and group.
pub fn replace(path: &Path, text: &str, keep: usize) -> std::io::Result<()> {
    let dir = directory(path);
    let name = path.file_name().map_or_else(
        || "drivegate.toml".into(),
        |n| n.to_string_lossy().into_owned(),
    );
    let meta = std::fs::metadata(path)?;
    let mode = meta.permissions().mode() & 0o7777;
    let temporary = dir.join(format!(".{name}.new"));
    // One left by a crash is ours to replace.
    let _ = std::fs::remove_file(&temporary);
    let written = (|| {
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .mode(mode)
            .open(&temporary)?;
        file.write_all(text.as_bytes())?;
        keep_owner(&file, &meta);
        // The mode again: the process's umask took bits from it.
        file.set_permissions(std::fs::Permissions::from_mode(mode))?;
        file.sync_all()
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_file(&temporary);
        return Err(e);
    }
    if keep > 0 {
        shift_generations(path, keep);
    }
    if let Err(e) = std::fs::rename(&temporary, path) {
        let _ = std::fs::remove_file(&temporary);
        return Err(e);
    }
    std::fs::File::open(dir)?.sync_all()
}

/// The original's owner and group on `file`, or its group alone (a user
/// may give a file any group it is in), or neither: the service then owns
/// the new file, as it would any file it writes.
fn keep_owner(file: &std::fs::File, original: &std::fs::Metadata) {
    use std::os::unix::fs::fchown;
    if fchown(file, Some(original.uid()), Some(original.gid())).is_err() {
        let _ = fchown(file, None, Some(original.gid()));
    }
}

/// `<path>.1` .. `<path>.<keep - 1>` moved one up (the oldest dropped) and
/// the file as it is now linked as `<path>.1`. Best effort: a version
/// that cannot be kept does not stop the change.
fn shift_generations(path: &Path, keep: usize) {
    let _ = std::fs::remove_file(generation_path(path, keep));
    for n in (1..keep).rev() {
        let _ = std::fs::rename(generation_path(path, n), generation_path(path, n + 1));
    }
    let first = generation_path(path, 1);
    let _ = std::fs::remove_file(&first);
    if std::fs::hard_link(path, &first).is_err()
        && std::fs::copy(path, &first).is_ok()
        && let (Ok(meta), Ok(copy)) = (std::fs::metadata(path), std::fs::File::open(&first))
    {
        keep_owner(&copy, &meta);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_change_keeps_the_mode_and_the_previous_versions() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("drivegate.toml");
        std::fs::write(&path, "v0\n").unwrap();
        std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o640)).unwrap();
        for i in 1..=7 {
            replace(&path, &format!("v{i}\n"), GENERATIONS).unwrap();
        }
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "v7\n");
        let mode = std::fs::metadata(&path).unwrap().permissions().mode() & 0o7777;
        assert_eq!(mode, 0o640);
        let kept: Vec<(usize, String)> = generations(&path)
            .into_iter()
            .map(|g| (g.number, std::fs::read_to_string(g.path).unwrap()))
            .collect();
        let want: Vec<(usize, String)> = (1..=5).map(|n| (n, format!("v{}\n", 7 - n))).collect();
        assert_eq!(kept, want);
        for g in generations(&path) {
            let mode = std::fs::metadata(&g.path).unwrap().permissions().mode() & 0o7777;
            assert_eq!(mode, 0o640, "{}", g.path.display());
        }
        // Nothing else is left in the directory.
        let names = std::fs::read_dir(dir.path()).unwrap().count();
        assert_eq!(names, 1 + GENERATIONS);
        let v5 = version_with_sha(&path, &sha256_hex("v5\n"));
        assert_eq!(v5.as_deref(), Some("v5\n"));
        assert_eq!(version_with_sha(&path, &sha256_hex("v0\n")), None);
    }

    #[test]
    fn without_generations_only_the_file_changes() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plant.toml");
        std::fs::write(&path, "a\n").unwrap();
        replace(&path, "b\n", 0).unwrap();
        assert_eq!(std::fs::read_to_string(&path).unwrap(), "b\n");
        assert!(generations(&path).is_empty());
        assert!(may_write(&path).is_ok());
    }

    #[test]
    fn a_missing_file_is_not_created() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("absent.toml");
        assert!(replace(&path, "x\n", GENERATIONS).is_err());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        assert!(may_write(&dir.path().join("no/such/dir.toml")).is_err());
    }
}
