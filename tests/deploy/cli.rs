//! The command line: `check-config` on good and bad files.

use std::process::Command;

fn drivegate() -> Command {
    Command::new(env!("CARGO_BIN_EXE_drivegate"))
}

#[test]
fn check_config_accepts_the_reference_and_default_configs() {
    for file in ["config/drivegate.toml", "config/default.toml"] {
        let out = drivegate().args(["check-config", file]).output().unwrap();
        assert!(
            out.status.success(),
            "{file}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let stdout = String::from_utf8_lossy(&out.stdout);
        assert!(stdout.contains("valid"), "{stdout}");
    }
}

#[test]
fn check_config_points_at_the_line_and_column() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.toml");
    std::fs::write(
        &path,
        "[[bus]]\nname = \"line1\"\nport = \"sim\"\n[[bus.drive]]\nunit = 300\nname = \"a\"\n",
    )
    .unwrap();
    let out = drivegate().arg("check-config").arg(&path).output().unwrap();
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("bad.toml:5:8:")
            && stderr.contains("unit 300 is out of range: valid 1 to 255"),
        "{stderr}"
    );

    let out = drivegate()
        .args(["check-config", "/nonexistent/drivegate.toml"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("cannot read /nonexistent/drivegate.toml")
    );
}

#[test]
fn serve_refuses_a_bad_config_before_starting() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.toml");
    std::fs::write(&path, "[http]\nlisten = \"not an address\"\n").unwrap();
    let out = drivegate()
        .arg("serve")
        .arg("--config")
        .arg(&path)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("bad.toml:2:10:"), "{stderr}");
}
