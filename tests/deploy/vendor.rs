//! The OPC UA crates built from `vendor/` are the published ones with the
//! listed fixes and nothing else: each published `.crate` (checked against
//! its crates.io checksum), unpacked, with its patch of `vendor/` applied by
//! `git apply`, must be the vendored copy file for file.
//!
//! `scripts/test` puts the published crates in cargo's registry cache
//! (`cargo fetch --manifest-path vendor/published/Cargo.toml`): a build
//! alone does not, since the build uses the copies.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use sha2::{Digest, Sha256};

/// The vendored crates and the checksums crates.io gives for them (as any
/// `Cargo.lock` that uses them from the registry says).
const VENDORED: [(&str, &str); 2] = [
    (
        "async-opcua-nodes-0.19.0",
        "db978815d9226c4b718e4856912b97930cc54bd5810bc24b9766f8866ed34479",
    ),
    (
        "async-opcua-server-0.19.0",
        "8d1738e1141549d976e6f23cf1598e3dc02150c440c390ec7a72da6a2c6e4935",
    ),
];

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// The published `.crate` file in cargo's registry cache.
fn published(name: &str) -> PathBuf {
    let home = std::env::var_os("CARGO_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".cargo")))
        .expect("CARGO_HOME or HOME");
    let cache = home.join("registry/cache");
    let found = std::fs::read_dir(&cache)
        .into_iter()
        .flatten()
        .flatten()
        .map(|index| index.path().join(format!("{name}.crate")))
        .find(|p| p.is_file());
    found.unwrap_or_else(|| {
        panic!(
            "{name}.crate is not in {}: fetch the published crates with \
             `cargo fetch --locked --manifest-path vendor/published/Cargo.toml` (scripts/test does)",
            cache.display()
        )
    })
}

/// Every file under `dir`, by its path relative to it, with its bytes.
fn files(dir: &Path) -> BTreeMap<PathBuf, Vec<u8>> {
    fn walk(base: &Path, dir: &Path, out: &mut BTreeMap<PathBuf, Vec<u8>>) {
        for entry in std::fs::read_dir(dir).expect("a directory") {
            let path = entry.expect("an entry").path();
            if path.is_dir() {
                walk(base, &path, out);
            } else {
                let relative = path.strip_prefix(base).expect("under base").to_path_buf();
                out.insert(relative, std::fs::read(&path).expect("a file"));
            }
        }
    }
    let mut out = BTreeMap::new();
    walk(dir, dir, &mut out);
    out
}

fn run(command: &mut Command) {
    let output = command.output().expect("the command runs");
    assert!(
        output.status.success(),
        "{command:?}: {}{}",
        String::from_utf8_lossy(&output.stdout),
        String::from_utf8_lossy(&output.stderr)
    );
}

#[test]
fn the_vendored_crates_are_the_published_ones_with_their_patches() {
    for (name, checksum) in VENDORED {
        let crate_file = published(name);
        let bytes = std::fs::read(&crate_file).expect("the .crate file");
        let digest: String = Sha256::digest(&bytes)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect();
        assert_eq!(
            digest,
            checksum,
            "{} is not the crate crates.io published",
            crate_file.display()
        );
        let scratch = tempfile::tempdir().expect("a scratch directory");
        run(Command::new("tar")
            .arg("-xzf")
            .arg(&crate_file)
            .arg("-C")
            .arg(scratch.path()));
        let unpacked = scratch.path().join(name);
        let patch = root().join("vendor").join(format!("{name}.patch"));
        run(Command::new("git")
            .args(["apply", "--whitespace=nowarn"])
            .arg(&patch)
            .current_dir(&unpacked));
        let expected = files(&unpacked);
        let vendored = files(&root().join("vendor").join(name));
        let names = |m: &BTreeMap<PathBuf, Vec<u8>>| m.keys().cloned().collect::<Vec<_>>();
        assert_eq!(
            names(&vendored),
            names(&expected),
            "vendor/{name} has other files than the published crate"
        );
        for (path, bytes) in &expected {
            assert!(
                vendored.get(path) == Some(bytes),
                "vendor/{name}/{} differs from the published crate with vendor/{name}.patch: \
                 make the change in the patch too (vendor/README.md)",
                path.display()
            );
        }
        // The patch changes something in each of these crates.
        assert!(
            std::fs::read_to_string(&patch)
                .expect("the patch")
                .contains("\n+"),
            "{name}.patch is empty"
        );
    }
}

/// Every file a patch changes is named in `vendor/README.md`, and every
/// fix the README explains is in its table of which patch carries it: a
/// change to the published crates cannot go unexplained.
#[test]
fn every_change_of_the_patches_is_explained_in_the_readme() {
    let readme = std::fs::read_to_string(root().join("vendor/README.md")).expect("the README");
    for (name, _) in VENDORED {
        let patch = std::fs::read_to_string(root().join("vendor").join(format!("{name}.patch")))
            .expect("the patch");
        let changed: Vec<&str> = patch
            .lines()
            .filter_map(|l| l.strip_prefix("diff --git a/src/"))
            .filter_map(|l| l.split(' ').next())
            .collect();
        assert!(!changed.is_empty(), "{name}.patch changes no file");
        for file in changed {
            assert!(
                readme.contains(&format!("`{file}`")),
                "{name}.patch changes src/{file}, which vendor/README.md does not name"
            );
        }
    }
    // The fixes explained ("6. **...**"), and those the table assigns to a
    // patch ("| 3, 5, 6 |").
    let explained: Vec<u32> = readme
        .lines()
        .filter_map(|l| l.split_once(". **"))
        .filter_map(|(n, _)| n.trim().parse().ok())
        .collect();
    let mut assigned: Vec<u32> = readme
        .lines()
        .filter(|l| l.contains(".patch`"))
        .filter_map(|l| l.trim_end_matches('|').rsplit('|').next())
        .flat_map(|cell| cell.split(',').map(|n| n.trim().parse::<u32>()))
        .collect::<Result<_, _>>()
        .expect("the table's last column lists fix numbers");
    assigned.sort_unstable();
    assert!(!explained.is_empty(), "vendor/README.md explains no fix");
    assert_eq!(
        assigned, explained,
        "vendor/README.md: the table assigns other fixes than it explains"
    );
}
