//! The third-party tools the tests run, and how to get one that is
//! missing: a missing tool fails its test saying so, it never skips it.
//! `scripts/test` installs them all; it is also where they are listed, so
//! a tool the tests run and the script does not install cannot go unseen.

use std::path::Path;

/// `scripts/test`, whose `TOOLS` (command:Debian package) and `PY_PINS`
/// (pip requirement) lists say where each tool comes from.
const SCRIPT: &str = include_str!("../../scripts/test");

/// How to get `tool` (a command, or a Python package the tests import).
pub fn how_to_get(tool: &str) -> String {
    let python_package = match tool {
        "st" | "schemathesis" => Some("schemathesis"),
        "pymodbus" => Some("pymodbus"),
        "pysparkplug" => Some("pysparkplug"),
        _ => None,
    };
    if let Some(package) = python_package {
        let pin = SCRIPT
            .lines()
            .map(|l| l.trim().trim_matches('"'))
            .find(|l| l.starts_with(&format!("{package}==")))
            .unwrap_or_else(|| {
                panic!("scripts/test pins no version of {package}: add it to PY_PINS")
            });
        return format!(
            "`scripts/test` installs it into target/pyenv; by hand: `pip install '{pin}'` into a virtual environment first on the PATH"
        );
    }
    let package = SCRIPT
        .lines()
        .find_map(|l| l.trim().strip_prefix(tool)?.strip_prefix(':'))
        .unwrap_or_else(|| panic!("scripts/test does not install `{tool}`: add it to TOOLS"));
    format!("`scripts/test` installs it; by hand: `apt-get install {package}`")
}

/// The failure for a tool that could not be started.
pub fn cannot_run(tool: &str, error: &std::io::Error) -> String {
    format!("cannot run `{tool}` ({error}): {}", how_to_get(tool))
}

/// Fails the test, saying how to get it, unless `tool` is a command on
/// the PATH.
pub fn require(tool: &str) {
    let found = std::env::var_os("PATH")
        .map(|path| std::env::split_paths(&path).any(|dir| is_executable(&dir.join(tool))))
        .unwrap_or(false);
    assert!(found, "`{tool}` is not on the PATH: {}", how_to_get(tool));
}

fn is_executable(path: &Path) -> bool {
    use std::os::unix::fs::PermissionsExt;
    path.metadata()
        .map(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
        .unwrap_or(false)
}
