//! The command line: `check-config` on good and bad files (the common
//! mistakes of a hand-written file in plain words, a baud rate that is
//! probably a typo), `--help`, and `token new`.

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

/// `check-config` on `text`: its exit code, stdout and stderr.
fn check(text: &str) -> (Option<i32>, String, String) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("plant.toml");
    std::fs::write(&path, text).unwrap();
    // Named as a user names it, from where it is.
    let out = drivegate()
        .args(["check-config", "plant.toml"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    (
        out.status.code(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[test]
fn the_common_mistakes_are_said_in_plain_words_with_the_right_form() {
    // Each mistake as a plant engineer makes it, the position, and the
    // right form in the message.
    let cases = [
        (
            "[bus]\nname = \"line1\"\nport = \"sim\"\n",
            "plant.toml:1:1: [bus] must be written [[bus]] (two brackets)",
        ),
        (
            "[[bus]]\nname = \"line1\"\nport = \"sim\"\n\n[bus.drive]\nunit = 1\nname = \"conveyor\"\n",
            "plant.toml:5:1: [bus.drive] must be written [[bus.drive]] (two brackets)",
        ),
        (
            "[[safety]]\non_shutdown = \"brake\"\n",
            "plant.toml:2:1: [[safety]] must be written [safety] (one pair of brackets)",
        ),
        (
            "[http]\nlisten = \"8080\"\n",
            "plant.toml:2:10: listen = \"8080\" is a port without an address: write \
             listen = \"0.0.0.0:8080\" (every network interface) or listen = \"127.0.0.1:8080\" \
             (this machine only)",
        ),
        (
            "[[bus]]\nname = \"line1\"\nport = \"sim\"\nbaud = \"115200\"\n",
            "plant.toml:4:8: baud = \"115200\": numbers are written without quotes: baud = 115200",
        ),
        (
            "[safety]\non_shutdown = brake\n",
            "plant.toml:2:15: on_shutdown = brake: text is written in quotes: on_shutdown = \"brake\"",
        ),
    ];
    for (text, wanted) in cases {
        let (code, _, stderr) = check(text);
        assert_eq!(code, Some(1), "{text}");
        assert!(stderr.starts_with(wanted), "{text}\n{stderr}");
    }
}

#[test]
fn mqtt_commands_from_any_client_of_the_broker_are_warned_by_check_config() {
    let mqtt = "[mqtt]\nbroker = \"mqtt://127.0.0.1:1883\"\ncommands = \"operator\"\n";
    let (code, stdout, stderr) = check(&format!("{mqtt}unauthenticated_commands = true\n"));
    // Valid (a test bench may mean it), and said, where the key is.
    assert_eq!(code, Some(0), "{stderr}");
    assert!(stdout.contains("valid (0 bus(es), 0 drive(s))"), "{stdout}");
    assert!(
        stderr.starts_with(
            "warning: plant.toml:4:28: [mqtt] unauthenticated_commands = true: commands are \
             taken from any client of the broker"
        ) && stderr.contains("the audit log names them \"unauthenticated broker 127.0.0.1:1883\"")
            && stderr.contains("username and password_file")
            && stderr.contains("client certificate over mqtts://"),
        "{stderr}"
    );
    assert_eq!(stderr.lines().count(), 1, "{stderr}");
    // Without it, the file is refused (commands need a login); with a
    // login, the key takes no effect and nothing is said.
    let dir = tempfile::tempdir().unwrap();
    let password = dir.path().join("mqtt-password");
    std::fs::write(&password, "secret\n").unwrap();
    let (code, _, stderr) = check(&format!(
        "{mqtt}unauthenticated_commands = true\nusername = \"gw1\"\npassword_file = \"{}\"\n",
        password.display()
    ));
    assert_eq!(code, Some(0), "{stderr}");
    assert!(!stderr.contains("warning"), "{stderr}");
}

#[test]
fn a_baud_rate_that_is_no_standard_one_is_warned_with_the_rate_meant() {
    let (code, stdout, stderr) = check(
        "[[bus]]\nname = \"line1\"\nport = \"sim\"\nbaud = 11520\n\n[[bus.drive]]\nunit = 1\nname = \"conveyor\"\n",
    );
    // Valid (an unusual rate may be meant), and said.
    assert_eq!(code, Some(0), "{stderr}");
    assert!(stdout.contains("valid (1 bus(es), 1 drive(s))"), "{stdout}");
    assert!(
        stderr.starts_with(
            "warning: plant.toml:4:8: bus \"line1\": baud = 11520 is not a standard rate \
             (did you mean 115200?): a drive at another rate never answers."
        ) && stderr.contains("9600, 19200, 38400, 57600, 115200")
            && stderr.contains("--try-bauds"),
        "{stderr}"
    );
    let (code, _, stderr) = check("[[bus]]\nname = \"line1\"\nport = \"sim\"\nbaud = 19200\n");
    assert_eq!(code, Some(0));
    assert!(stderr.is_empty(), "{stderr}");
}

#[test]
fn help_names_every_face() {
    let out = drivegate().arg("--help").output().unwrap();
    assert!(out.status.success());
    let help = String::from_utf8_lossy(&out.stdout);
    for face in [
        "REST",
        "WebSocket",
        "Modbus TCP",
        "Modbus/TCP Security",
        "OPC UA",
        "MQTT",
        "Sparkplug B",
        "JSON",
        "Prometheus",
        "web console",
    ] {
        assert!(help.contains(face), "--help does not name {face}:\n{help}");
    }
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

/// The lines `token new` prints, pasted into a configuration, make the
/// daemon accept the printed token with the printed name and role.
#[tokio::test]
async fn a_token_made_by_the_tool_authenticates_once_pasted() {
    let out = drivegate()
        .args(["token", "new", "--name", "scada", "--role", "operator"])
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8(out.stdout).unwrap();
    // The token is the only indented line; the lines to paste start at
    // the table's header and run to the end.
    let token = stdout
        .lines()
        .find_map(|l| l.strip_prefix("    "))
        .unwrap_or_else(|| panic!("no token in {stdout}"))
        .to_string();
    assert_eq!(token.len(), 64, "{stdout}");
    assert_eq!(stdout.matches(&token).count(), 1, "printed once");
    let lines = &stdout[stdout.find("[[http.token]]").expect("lines to paste")..];
    assert!(!lines.contains(&token), "the lines hold no secret");
    // What the first token changes, and how to keep an admin.
    let before = &stdout[..stdout.find("[[http.token]]").unwrap()];
    assert!(
        before.contains("every client\nneeds a token, on this machine (loopback) too")
            && before.contains("drivegate token new --name NAME --role admin"),
        "{stdout}"
    );

    let config = format!("{}\n{lines}", crate::support::FOUR_DRIVES);
    let daemon = crate::support::TestDaemon::start_no_wait(&config).await;
    let api = crate::support::api::Api::new(daemon.http, Some(&token));
    let me = api.get("/api/v1/whoami").await.expect(200);
    assert_eq!(me["who"], "scada", "{me}");
    assert_eq!(me["role"], "operator", "{me}");
    api.with_token(None)
        .get("/api/v1/drives")
        .await
        .expect_problem(401, "unauthorized");
    let mut wrong = token.clone();
    wrong.replace_range(..1, if token.starts_with('0') { "1" } else { "0" });
    api.with_token(Some(&wrong))
        .get("/api/v1/drives")
        .await
        .expect_problem(401, "unauthorized");
    daemon.stop().await;

    // An admin's token needs no advice to make one.
    let out = drivegate()
        .args(["token", "new", "--name", "ops", "--role", "admin"])
        .output()
        .unwrap();
    let stdout = String::from_utf8(out.stdout).unwrap();
    assert!(
        stdout.contains("on this machine (loopback) too"),
        "{stdout}"
    );
    assert!(!stdout.contains("--role admin"), "{stdout}");

    let out = drivegate()
        .args(["token", "new", "--name", "scada", "--role", "root"])
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
    assert!(
        String::from_utf8_lossy(&out.stderr)
            .contains("role must be one of viewer, operator, admin")
    );
}

#[test]
fn check_config_warns_of_plain_admin_networks_and_the_old_default() {
    let dir = tempfile::tempdir().unwrap();
    let check = |name: &str, modbus_tcp: &str| {
        let path = dir.path().join(name);
        std::fs::write(&path, format!("[modbus_tcp]\n{modbus_tcp}\n")).unwrap();
        let out = drivegate().arg("check-config").arg(&path).output().unwrap();
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    };
    // A plant network with the admin role over plain Modbus TCP.
    let out = check(
        "admin.toml",
        "listen = \"0.0.0.0:502\"\nallowed_networks = [\"127.0.0.0/8\", \"10.0.0.0/8\"]",
    );
    let warnings: Vec<&str> = out.lines().filter(|l| l.starts_with("warning: ")).collect();
    assert_eq!(warnings.len(), 1, "{out}");
    assert!(
        warnings[0].contains("gives 10.0.0.0/8 the admin role over plain Modbus TCP")
            && warnings[0].contains("Modbus/TCP Security"),
        "{out}"
    );
    // A file that relied on the private ranges being let in by default.
    let out = check("old.toml", "listen = \"0.0.0.0:502\"");
    assert!(
        out.contains("warning: Modbus TCP listens on 0.0.0.0:502 but admits loopback only")
            && out.contains("[[modbus_tcp.clients]]"),
        "{out}"
    );
    // Plant networks with a role each, on loopback: nothing to say.
    let out = check(
        "new.toml",
        "[[modbus_tcp.clients]]\nnetwork = \"10.0.5.0/24\"\nrole = \"operator\"",
    );
    assert!(!out.contains("warning"), "{out}");
}
