//! The Debian package's contents as `cargo deb` takes them from Cargo.toml:
//! every file exists, the default configuration is valid for the binary,
//! and the maintainer scripts create the service's user before the unit
//! starts. (Building the .deb itself is a separate command, see
//! docs/operations.md.)

use std::path::Path;
use std::time::Duration;

use tokio::process::Command;

const ROOT: &str = env!("CARGO_MANIFEST_DIR");
const UNIT: &str = include_str!("../../deploy/systemd/drivegate.service");

fn deb_metadata() -> toml::Table {
    let text = std::fs::read_to_string(Path::new(ROOT).join("Cargo.toml")).unwrap();
    let manifest: toml::Table = text.parse().unwrap();
    manifest["package"]["metadata"]["deb"]
        .as_table()
        .expect("[package.metadata.deb]")
        .clone()
}

async fn run(program: &str, args: &[&str]) -> (bool, String) {
    let out = tokio::time::timeout(
        Duration::from_secs(20),
        Command::new(program)
            .args(args)
            .current_dir(ROOT)
            .kill_on_drop(true)
            .output(),
    )
    .await
    .expect("in time")
    .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    (out.status.success(), text)
}

#[test]
fn every_asset_exists_and_the_unit_and_config_are_in_place() {
    let deb = deb_metadata();
    let assets = deb["assets"].as_array().unwrap();
    let mut destinations = Vec::new();
    for asset in assets {
        let a = asset.as_array().unwrap();
        let (source, dest) = (a[0].as_str().unwrap(), a[1].as_str().unwrap());
        // The binary is built by `cargo deb` itself.
        if source != "target/release/drivegate" {
            assert!(Path::new(ROOT).join(source).is_file(), "{source} missing");
        }
        destinations.push(dest.to_string());
    }
    assert!(destinations.iter().any(|d| d == "usr/bin/"));
    // The user comes from postinst (adduser): a file in sysusers.d would make
    // cargo-deb add a systemd-sysusers call, which fails where that tool is
    // not installed (containers, chroots).
    assert!(
        destinations.iter().all(|d| !d.contains("sysusers.d")),
        "{destinations:?}"
    );
    assert!(
        destinations
            .iter()
            .any(|d| d == "etc/drivegate/drivegate.toml")
    );
    let conf_files: Vec<&str> = deb["conf-files"]
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_str().unwrap())
        .collect();
    assert_eq!(conf_files, ["/etc/drivegate/drivegate.toml"]);
    // The unit the package installs is the one in deploy/systemd, and it
    // reads the configuration the package installs.
    let units = deb["systemd-units"].as_table().unwrap();
    assert_eq!(units["unit-name"].as_str(), Some("drivegate"));
    let dir = Path::new(ROOT).join(units["unit-scripts"].as_str().unwrap());
    assert!(dir.join("drivegate.service").is_file());
    assert!(UNIT.contains("--config /etc/drivegate/drivegate.toml"));
    assert!(deb["depends"].as_str().unwrap().contains("adduser"));
}

#[test]
fn postinst_creates_the_user_before_the_unit_starts() {
    let deb = deb_metadata();
    let dir = Path::new(ROOT).join(deb["maintainer-scripts"].as_str().unwrap());
    let postinst = std::fs::read_to_string(dir.join("postinst")).unwrap();
    let user = postinst
        .find("adduser --system")
        .expect("system user created");
    let dialout = postinst
        .find("adduser --quiet drivegate dialout")
        .expect("user put in dialout");
    // cargo-deb puts the unit's enable/start snippet at #DEBHELPER#.
    let snippet = postinst.find("#DEBHELPER#").expect("#DEBHELPER# token");
    assert!(user < snippet && dialout < snippet);
    assert!(
        UNIT.lines().any(|l| l == "User=drivegate"),
        "the unit runs as the user postinst creates"
    );
}

#[tokio::test]
async fn maintainer_scripts_are_valid_shell() {
    for script in ["deploy/debian/postinst", "deploy/debian/postrm"] {
        let (ok, out) = run("sh", &["-n", script]).await;
        assert!(ok, "{script}: {out}");
        let mode = std::fs::metadata(Path::new(ROOT).join(script))
            .unwrap()
            .permissions();
        use std::os::unix::fs::PermissionsExt;
        assert_eq!(mode.mode() & 0o111, 0o111, "{script} is not executable");
    }
}

#[tokio::test]
async fn packaged_configuration_is_valid_and_real() {
    let bin = env!("CARGO_BIN_EXE_drivegate");
    let (ok, out) = run(bin, &["check-config", "deploy/debian/drivegate.toml"]).await;
    assert!(ok, "{out}");
    let config =
        std::fs::read_to_string(Path::new(ROOT).join("deploy/debian/drivegate.toml")).unwrap();
    let config: toml::Table = config.parse().unwrap();
    // The package waits to be configured: no bus polls a guessed port
    // (docs/operations.md says why).
    assert!(config.get("bus").is_none(), "{config:?}");
    // Modbus TCP on the standard port (the unit grants the capability).
    assert!(
        config["modbus_tcp"]["listen"]
            .as_str()
            .unwrap()
            .ends_with(":502")
    );
    assert!(UNIT.contains("AmbientCapabilities=CAP_NET_BIND_SERVICE"));
    // The reference file shipped as the example is valid too.
    let (ok, out) = run(bin, &["check-config", "config/drivegate.toml"]).await;
    assert!(ok, "{out}");
}

/// The daemon started with the shipped configuration serves, polls
/// nothing, and `/readyz` (which the console's message matches) says
/// what to do first.
#[tokio::test]
async fn the_shipped_configuration_waits_to_be_configured() {
    let text =
        std::fs::read_to_string(Path::new(ROOT).join("deploy/debian/drivegate.toml")).unwrap();
    let text = crate::support::replaced(&text, "127.0.0.1:8080", "127.0.0.1:0");
    let text = crate::support::replaced(&text, "127.0.0.1:502", "127.0.0.1:0");
    let d = crate::support::TestDaemon::start_no_wait(&text).await;
    assert!(d.plant.buses().is_empty());
    let r = reqwest::get(d.url("/readyz")).await.unwrap();
    assert_eq!(r.status(), 503);
    let ready: serde_json::Value = r.json().await.unwrap();
    assert_eq!(
        ready["reasons"],
        serde_json::json!([drivegate::api::health::NO_BUS])
    );
    let console = reqwest::get(d.url("/console/pages/overview.js"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(
        console.contains("No bus configured: run "),
        "the console says it too"
    );
    assert!(console.contains("drivegate probe --port /dev/serial/by-id/..."));
    d.stop().await;
}
