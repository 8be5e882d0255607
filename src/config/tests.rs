//! Configuration parsing and validation, with the positions errors point at.

use super::*;

fn parse(text: &str) -> Result<Config, ConfigError> {
    Config::parse(text, "test.toml")
}

fn err(text: &str) -> String {
    parse(text).unwrap_err().to_string()
}

const MINIMAL: &str = r#"
[[bus]]
name = "line1"
port = "/dev/ttyUSB0"

[[bus.drive]]
unit = 1
name = "conveyor"
gear_ratio = 3.75
"#;

#[test]
fn embedded_default_is_valid() {
    let c = Config::embedded_default().unwrap();
    assert_eq!(c.buses.len(), 1);
    assert!(c.buses[0].is_simulated());
    assert_eq!(c.drive_count(), 4);
    assert_eq!(c.http.listen.to_string(), "127.0.0.1:8080");
    assert_eq!(c.modbus_tcp.listen.to_string(), "127.0.0.1:5020");
}

#[test]
fn the_documented_reference_config_is_valid() {
    let text = include_str!("../../config/drivegate.toml");
    let c = parse(text).unwrap();
    assert!(!c.buses.is_empty());
}

#[test]
fn defaults_fill_in() {
    let c = parse(MINIMAL).unwrap();
    let bus = &c.buses[0];
    assert_eq!(
        (
            bus.baud,
            bus.response_timeout_ms,
            bus.retries,
            bus.poll_interval_ms
        ),
        (115200, 50, 1, 0)
    );
    let s = bus.settings("/dev/ttyUSB0");
    assert_eq!(s.drives, vec![(1, std::time::Duration::ZERO)]);
    assert_eq!(s.master.guard, crate::bus::master::Guard::Auto);
    assert_eq!(bus.drives[0].gear_ratio, 3.75);
    // A guard given is kept after every fault.
    let c = parse(&MINIMAL.replace("[[bus]]", "[[bus]]\nguard_ms = 80")).unwrap();
    assert_eq!(
        c.buses[0].settings("/dev/ttyUSB0").master.guard,
        crate::bus::master::Guard::Fixed(std::time::Duration::from_millis(80))
    );
}

#[test]
fn the_interface_example_of_the_docs_parses() {
    let c = parse(
        r#"
[http]
listen = "127.0.0.1:8080"
[modbus_tcp]
listen = "127.0.0.1:5020"
[[bus]]
name = "line1"
port = "/dev/ttyUSB0"      # or "tcp://host:port", or "sim" for the built-in simulator
baud = 115200
response_timeout_ms = 50
retries = 1
poll_interval_ms = 0       # per drive; 0 = as fast as the bus allows
[[bus.drive]]
unit = 1
name = "conveyor"
gear_ratio = 3.75
"#,
    )
    .unwrap();
    assert_eq!(c.buses[0].drives[0].name(), "conveyor");
}

#[test]
fn unknown_keys_are_refused_with_their_position() {
    let e = err(&MINIMAL
        .replace("retries", "x")
        .replace("gear_ratio = 3.75", "gear_ratio = 3.75\nspeed = 3"));
    assert!(
        e.starts_with("test.toml:10:1: unknown field `speed`"),
        "{e}"
    );
}

#[test]
fn out_of_range_values_name_the_range_and_position() {
    let e = err(&MINIMAL.replace("unit = 1", "unit = 0"));
    assert!(e.starts_with("test.toml:7:8:"), "{e}");
    assert!(e.contains("valid 1 to 255"), "{e}");
    let e = err(&MINIMAL.replace("gear_ratio = 3.75", "gear_ratio = -1"));
    assert!(
        e.contains("test.toml:9:14") && e.contains("gear ratio -1 is out of range"),
        "{e}"
    );
    let text = MINIMAL.replace(
        "port = \"/dev/ttyUSB0\"",
        "port = \"/dev/ttyUSB0\"\nresponse_timeout_ms = 0",
    );
    let e = err(&text);
    assert!(
        e.contains(":5:23:") && e.contains("valid 1 to 10000"),
        "{e}"
    );
}

#[test]
fn duplicates_are_refused_where_they_are() {
    let twice = format!("{MINIMAL}\n[[bus.drive]]\nunit = 1\nname = \"other\"\n");
    let e = err(&twice);
    assert!(
        e.contains("test.toml:12:8: unit 1 is used twice on bus \"line1\""),
        "{e}"
    );

    let same_name = format!("{MINIMAL}\n[[bus.drive]]\nunit = 2\nname = \"conveyor\"\n");
    let e = err(&same_name);
    assert!(
        e.contains("test.toml:13:8: drive name \"conveyor\" is already used"),
        "{e}"
    );

    let two_buses = format!(
        "{MINIMAL}\n[[bus]]\nname = \"line1\"\nport = \"sim\"\n[[bus.drive]]\nunit = 1\nname = \"b\"\n"
    );
    let e = err(&two_buses);
    assert!(e.contains("bus name \"line1\" is used twice"), "{e}");

    let same_port = format!(
        "{MINIMAL}\n[[bus]]\nname = \"line2\"\nport = \"/dev/ttyUSB0\"\n[[bus.drive]]\nunit = 1\nname = \"b\"\n"
    );
    let e = err(&same_port);
    assert!(e.contains("port /dev/ttyUSB0 is used by two buses"), "{e}");
}

#[test]
fn names_are_checked() {
    let e = err(&MINIMAL.replace("name = \"conveyor\"", "name = \"42\""));
    assert!(e.contains("must not be only digits"), "{e}");
    let e = err(&MINIMAL.replace("name = \"conveyor\"", "name = \"a b\""));
    assert!(e.contains("letters, digits"), "{e}");
}

#[test]
fn a_config_may_have_no_bus_or_a_bus_without_drives() {
    let c = Config::parse("[http]\nlisten = \"127.0.0.1:1\"\n", "test.toml").unwrap();
    assert!(c.buses.is_empty());
    let c = Config::parse(
        "[[bus]]\nname = \"a\"\nport = \"/dev/ttyUSB0\"\n",
        "test.toml",
    )
    .unwrap();
    assert_eq!((c.buses.len(), c.drive_count()), (1, 0));
    // A simulated bus without drives is a silent line.
    let c = Config::parse("[[bus]]\nname = \"a\"\nport = \"sim\"\n", "test.toml").unwrap();
    assert!(c.buses[0].sim_config().validate().is_ok());
}

#[test]
fn not_toml_at_all() {
    let e = err("[[bus]\nname=");
    assert!(e.starts_with("test.toml:1:"), "{e}");
}

#[test]
fn sim_section_only_for_sim() {
    let e = err(&MINIMAL.replace("[[bus.drive]]", "[bus.sim]\nseed = 3\n\n[[bus.drive]]"));
    assert!(e.contains("only applies to port = \"sim\""), "{e}");
    let c = parse(&MINIMAL.replace("/dev/ttyUSB0", "sim").replace("[[bus.drive]]", "[bus.sim]\nseed = 3\nturnaround_ms = 0\n[bus.sim.faults]\ndrop_rate = 0.05\n\n[[bus.drive]]")).unwrap();
    let sim = c.buses[0].sim_config();
    assert_eq!(
        (sim.seed, sim.turnaround_ms, sim.faults.drop_rate),
        (3, 0.0, 0.05)
    );
    assert_eq!(sim.drives[0].gear_ratio, 3.75);
}

#[test]
fn serial_device_servers_are_ports_too() {
    let tcp = MINIMAL.replace("/dev/ttyUSB0", "tcp://192.168.127.254:4001");
    let c = parse(&tcp).unwrap();
    assert_eq!(
        c.buses[0].settings("tcp://192.168.127.254:4001").port,
        "tcp://192.168.127.254:4001"
    );
    // Mistakes point at the port, with the form to use.
    let e = err(&MINIMAL.replace("/dev/ttyUSB0", "tcp://192.168.127.254"));
    assert!(e.starts_with("test.toml:4:8: "), "{e}");
    assert!(
        e.contains("has no port number") && e.contains("tcp://host:port"),
        "{e}"
    );
    let e = err(&MINIMAL.replace("/dev/ttyUSB0", "tcp://nport:70000"));
    assert!(e.contains("1 to 65535"), "{e}");
    // Direction control is the device server's.
    let e = err(&format!("{tcp}\n[bus.rs485]\ndirection = \"rts\"\n"));
    assert!(
        e.starts_with("test.toml:4:8: ") && e.contains("serial device server"),
        "{e}"
    );
    // One bus per device server port.
    let e = err(&format!(
        "{tcp}\n[[bus]]\nname = \"line2\"\nport = \"tcp://192.168.127.254:4001\"\n[[bus.drive]]\nunit = 1\nname = \"b\"\n"
    ));
    assert!(e.contains("is used by two buses"), "{e}");
}

#[test]
fn monitor_and_scope_sections() {
    let c = parse(MINIMAL).unwrap();
    assert_eq!(c.monitor, MonitorConfig::default());
    assert!(c.monitor.enabled);
    assert_eq!(c.scope.floor_rate_hz, 10.0);
    let c = parse(&format!(
        "[monitor]\nenabled = false\nring_frames = 500\n[scope]\nmax_samples = 5000\nfloor_rate_hz = 2.5\n{MINIMAL}"
    ))
    .unwrap();
    assert_eq!(c.monitor.settings().ring_frames, 500);
    assert_eq!(c.monitor.memory_per_bus(), 0);
    assert_eq!(c.scope.settings().max_samples, 5000);
    let e = err(&format!("[scope]\nfloor_rate_hz = 0\n{MINIMAL}"));
    assert!(e.contains("2:17") && e.contains("0.1 to 100"), "{e}");
    let e = err(&format!("[monitor]\nring_frames = 5\n{MINIMAL}"));
    assert!(e.contains("2:15") && e.contains("16 to 1000000"), "{e}");
    let e = err(&format!("[scope]\nmax_sample = 5\n{MINIMAL}"));
    assert!(e.contains("2:1") && e.contains("max_sample"), "{e}");
}

#[test]
fn the_console_jog_lease_is_bounded() {
    let c = parse(MINIMAL).unwrap();
    assert_eq!(c.safety.jog_lease_ms, 300);
    let c = parse(&format!("[safety]\njog_lease_ms = 1500\n{MINIMAL}")).unwrap();
    assert_eq!(c.safety.jog_lease_ms, 1500);
    let e = err(&format!("[safety]\njog_lease_ms = 50\n{MINIMAL}"));
    assert!(e.contains("2:16") && e.contains("100 to 5000"), "{e}");
}

#[test]
fn lease_bounds_are_the_cores_and_bound_the_default_lease() {
    let c = parse(MINIMAL).unwrap();
    assert_eq!(
        (c.safety.lease_min_ms, c.safety.lease_max_ms),
        (100, 60_000)
    );
    let c = parse(&format!(
        "[safety]\nlease_min_ms = 50\nlease_max_ms = 2000\n{MINIMAL}"
    ))
    .unwrap();
    assert_eq!((c.safety.lease_min_ms, c.safety.lease_max_ms), (50, 2000));
    let e = err(&format!(
        "[safety]\nlease_min_ms = 500\nlease_max_ms = 100\n{MINIMAL}"
    ));
    assert!(
        e.contains("lease_max_ms = 100 is out of range: valid 500"),
        "{e}"
    );
    let e = err(&format!(
        "[http]\nlease_default_ms = 5000\n[safety]\nlease_max_ms = 1000\n{MINIMAL}"
    ));
    assert!(
        e.contains("lease_default_ms = 5000 is out of range: valid 100 to 1000"),
        "{e}"
    );
    let e = err(&format!("[safety]\nlease_min_ms = 500\n{MINIMAL}"));
    assert!(
        e.contains("jog_lease_ms = 300 is out of range: valid 500"),
        "{e}"
    );
    let e = err(&format!("[http]\nlease_min_ms = 100\n{MINIMAL}"));
    assert!(e.contains("moved to [safety] lease_min_ms"), "{e}");
}

#[test]
fn declared_settings_are_checked_at_load() {
    let text = format!(
        "{MINIMAL}\n[bus.drive.settings]\napply_settings = \"on-drift\"\ninertia_ratio = 5\n[bus.drive.settings.speed_ramp]\nalpha = 5000\n[bus.drive.settings.protection]\nlimit_a = 12.0\nstall_ms = 500\n"
    );
    let c = parse(&text).unwrap();
    let declared = c.buses[0].drives[0].declared().unwrap();
    assert_eq!(declared.apply, ApplySettings::OnDrift);
    assert!(!declared.save);
    assert_eq!(declared.wanted.inertia_ratio, Some(5));
    assert_eq!(declared.wanted.speed_alpha, Some(5000));
    assert_eq!(declared.wanted.limit_counts, Some(1536));
    assert_eq!(declared.wanted.position_alpha, None);
    // Without apply_settings it only reports.
    let c = parse(&format!(
        "{MINIMAL}\n[bus.drive.settings]\ninertia_ratio = 2\n"
    ))
    .unwrap();
    assert_eq!(
        c.buses[0].drives[0].declared().unwrap().apply,
        ApplySettings::Never
    );
    // Every value out of range is named, with its range and position.
    let e = err(&format!(
        "{MINIMAL}\n[bus.drive.settings]\ninertia_ratio = 0\n[bus.drive.settings.protection]\nstall_ms = 70000\n"
    ));
    assert!(
        e.contains("protection.stall_ms: stall time 70000 ms is out of range: valid 0 to 60000 ms"),
        "{e}"
    );
    assert!(
        e.contains("inertia_ratio: load inertia ratio 0 is out of range: valid 1 to 65535"),
        "{e}"
    );
    assert!(e.contains("test.toml:"), "{e}");
    let e = err(&format!("{MINIMAL}\n[bus.drive.settings]\nsave = true\n"));
    assert!(e.contains("declares no setting"), "{e}");
    let e = err(&format!(
        "{MINIMAL}\n[bus.drive.settings]\napply_settings = \"always\"\n"
    ));
    assert!(e.contains("never") && e.contains("on-drift"), "{e}");
    let e = err(&format!("{MINIMAL}\n[bus.drive.settings]\ninertia = 2\n"));
    assert!(e.contains("inertia"), "{e}");
}
