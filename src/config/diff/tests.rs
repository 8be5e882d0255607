//! The comparison of two configurations, section by section.

use super::*;

fn parse(text: &str) -> Config {
    match Config::parse(text, "test.toml") {
        Ok(c) => c,
        Err(e) => panic!("{e}"),
    }
}

const BASE: &str = r#"
[http]
listen = "127.0.0.1:8080"
[[http.token]]
name = "panel"
role = "operator"
sha256 = "0000000000000000000000000000000000000000000000000000000000000000"
[modbus_tcp]
listen = "127.0.0.1:5020"
[[bus]]
name = "line1"
port = "sim"
[[bus.drive]]
unit = 1
name = "conveyor"
[[bus.drive]]
unit = 2
name = "mixer"
[[bus]]
name = "line2"
port = "sim"
[[bus.drive]]
unit = 1
name = "press"
"#;

fn changed(from: &str, to: &str) -> Changes {
    diff(&parse(BASE), &parse(&BASE.replace(from, to)))
}

#[test]
fn the_same_file_changes_nothing() {
    let c = diff(&parse(BASE), &parse(BASE));
    assert!(c.is_empty(), "{c:?}");
    assert_eq!(c.lines(), vec!["no change"]);
}

#[test]
fn comments_and_moved_lines_change_nothing() {
    let moved = format!(
        "# a comment\n\n{}",
        BASE.replace("unit = 1\nname = \"press\"", "name = \"press\"\nunit = 1")
    );
    assert!(diff(&parse(BASE), &parse(&moved)).is_empty());
}

#[test]
fn a_drive_added_changes_only_its_bus_in_place() {
    let c = changed(
        "name = \"press\"\n",
        "name = \"press\"\n[[bus.drive]]\nunit = 2\nname = \"saw\"\n",
    );
    assert_eq!(c.drives_added, vec!["saw"]);
    assert!(c.drives_removed.is_empty() && c.drives_changed.is_empty());
    assert!(c.buses_reopened.is_empty(), "{c:?}");
    assert_eq!(
        c.buses_retuned,
        vec![("line2".to_string(), vec!["drives".to_string()])]
    );
    assert!(c.buses_added.is_empty() && c.buses_removed.is_empty());
    assert!(c.faces_restarted.is_empty() && c.sections.is_empty());
    assert_eq!(
        c.lines(),
        vec![
            "drives added: saw",
            "bus line2 changed in place (drives), its port kept open"
        ]
    );
}

#[test]
fn a_drive_removed() {
    let c = changed("[[bus.drive]]\nunit = 2\nname = \"mixer\"\n", "");
    assert_eq!(c.drives_removed, vec!["mixer"]);
    assert_eq!(c.buses_retuned[0].0, "line1");
    assert!(c.buses_reopened.is_empty());
}

#[test]
fn a_drive_renamed_is_the_same_drive_under_a_new_name() {
    let c = changed("unit = 2\nname = \"mixer\"", "unit = 2\nname = \"blender\"");
    assert_eq!(
        c.drives_renamed,
        vec![("mixer".to_string(), "blender".to_string())]
    );
    assert!(c.drives_added.is_empty() && c.drives_removed.is_empty());
    assert!(c.drives_changed.is_empty(), "{c:?}");
    assert_eq!(
        c.lines(),
        vec![
            "drives renamed: mixer to blender",
            "bus line1 changed in place (drives), its port kept open"
        ]
    );
    // Renamed and given another gear ratio: both said.
    let c = changed(
        "unit = 2\nname = \"mixer\"",
        "unit = 2\nname = \"blender\"\ngear_ratio = 5.0",
    );
    assert_eq!(c.drives_renamed.len(), 1);
    assert_eq!(c.drives_changed, vec!["blender"]);
    // Two drives swapping names: each motor keeps its unit, renamed.
    let swapped = BASE
        .replace("name = \"conveyor\"", "name = \"x\"")
        .replace("name = \"mixer\"", "name = \"conveyor\"")
        .replace("name = \"x\"", "name = \"mixer\"");
    let c = diff(&parse(BASE), &parse(&swapped));
    assert_eq!(c.drives_renamed.len(), 2, "{c:?}");
    assert!(c.drives_added.is_empty() && c.drives_removed.is_empty());
}

#[test]
fn which_changes_of_a_bus_reopen_it_and_which_apply_in_place() {
    let bus = |port: &str, keys: &str, drive: &str| {
        let text = format!(
            "[[bus]]\nname = \"line1\"\nport = \"{port}\"\n{keys}\n[[bus.drive]]\nunit = 1\nname = \"{drive}\"\n"
        );
        parse(&text).buses.remove(0)
    };
    let base = bus("/dev/ttyUSB0", "", "conveyor");
    let of = |keys: &str| bus_change(&base, &bus("/dev/ttyUSB0", keys, "conveyor"));
    assert_eq!(of(""), BusChange::default());
    for (keys, why) in [
        ("poll_interval_ms = 20", "poll rates"),
        ("response_timeout_ms = 200", "timing"),
        ("retries = 3", "timing"),
        ("guard_ms = 40", "timing"),
        ("broadcast_delay_ms = 40", "timing"),
        ("interframe = \"auto\"", "interframe"),
        ("reply_timeout_floor_ms = 9", "reply timeout floor"),
        ("offline_after = 5", "offline detection"),
        ("queue_capacity = 16", "queue"),
        ("poll_share = 2", "queue"),
    ] {
        let c = of(keys);
        assert!(c.reopen.is_empty(), "{keys}: {c:?}");
        assert_eq!(c.in_place, vec![why.to_string()], "{keys}");
    }
    let c = bus_change(&base, &bus("/dev/ttyUSB0", "", "belt"));
    assert_eq!(
        (c.reopen.len(), c.in_place),
        (0, vec!["drives".to_string()])
    );
    for (keys, why) in [
        ("baud = 57600", "baud"),
        ("[bus.rs485]\ndelay_after_send_us = 40", "rs485"),
    ] {
        assert_eq!(of(keys).reopen, vec![why.to_string()], "{keys}");
    }
    for port in ["/dev/ttyUSB1", "tcp://10.0.0.7:4001"] {
        let c = bus_change(&base, &bus(port, "", "conveyor"));
        assert_eq!(c.reopen, vec!["port".to_string()], "{port}");
    }
    let sim = bus("sim", "", "conveyor");
    let c = bus_change(&sim, &bus("sim", "[bus.sim]\nseed = 3", "conveyor"));
    assert_eq!(c.reopen, vec!["sim".to_string()]);
}

#[test]
fn a_drive_given_another_unit_is_removed_and_added() {
    let c = changed("unit = 2\nname = \"mixer\"", "unit = 3\nname = \"mixer\"");
    assert_eq!(c.drives_removed, vec!["mixer"]);
    assert_eq!(c.drives_added, vec!["mixer"]);
    assert!(c.drives_changed.is_empty());
}

#[test]
fn a_drive_moved_to_another_bus_is_removed_and_added() {
    let c = changed("[[bus.drive]]\nunit = 2\nname = \"mixer\"\n", "");
    let c2 = diff(
        &parse(BASE),
        &parse(
            &BASE
                .replace("[[bus.drive]]\nunit = 2\nname = \"mixer\"\n", "")
                .replace(
                    "name = \"press\"\n",
                    "name = \"press\"\n[[bus.drive]]\nunit = 2\nname = \"mixer\"\n",
                ),
        ),
    );
    assert_eq!(c.drives_removed, vec!["mixer"]);
    assert_eq!(c2.drives_removed, vec!["mixer"]);
    assert_eq!(c2.drives_added, vec!["mixer"]);
    let retuned: Vec<&str> = c2.buses_retuned.iter().map(|(b, _)| b.as_str()).collect();
    assert_eq!(retuned, vec!["line1", "line2"]);
}

#[test]
fn a_drive_poll_rate_is_a_change_of_the_drive() {
    let c = changed(
        "unit = 1\nname = \"press\"",
        "unit = 1\nname = \"press\"\npoll_interval_ms = 100",
    );
    assert_eq!(c.drives_changed, vec!["press"]);
    assert!(c.drives_added.is_empty() && c.drives_removed.is_empty());
}

#[test]
fn a_bus_port_or_baud_reopens_that_bus_only_with_what_else_changed() {
    let c = changed(
        "name = \"line2\"\nport = \"sim\"",
        "name = \"line2\"\nport = \"sim\"\nbaud = 57600\npoll_interval_ms = 20",
    );
    assert_eq!(
        c.buses_reopened,
        vec![(
            "line2".to_string(),
            vec!["baud".to_string(), "poll rates".to_string()]
        )]
    );
    assert!(c.drives_added.is_empty() && c.drives_changed.is_empty());
}

#[test]
fn the_silence_before_requests_changes_that_bus_in_place() {
    let c = changed(
        "name = \"line2\"\nport = \"sim\"",
        "name = \"line2\"\nport = \"sim\"\ninterframe = \"auto\"",
    );
    assert_eq!(
        c.buses_retuned,
        vec![("line2".to_string(), vec!["interframe".to_string()])]
    );
    assert!(c.buses_reopened.is_empty());
    let c = diff(
        &parse(&BASE.replace("port = \"sim\"", "port = \"sim\"\ninterframe = 400")),
        &parse(&BASE.replace("port = \"sim\"", "port = \"sim\"\ninterframe = 500")),
    );
    assert_eq!(c.buses_retuned.len(), 2, "{c:?}");
    // The default, written or not, is no change.
    assert!(
        changed("port = \"sim\"", "port = \"sim\"\ninterframe = \"spec\"")
            .buses_retuned
            .is_empty()
    );
}

#[test]
fn buses_added_and_removed_with_their_drives() {
    let c = changed("name = \"line2\"", "name = \"line3\"");
    assert_eq!(c.buses_added, vec!["line3"]);
    assert_eq!(c.buses_removed, vec!["line2"]);
    assert_eq!(c.drives_removed, vec!["press"]);
    assert_eq!(c.drives_added, vec!["press"]);
    assert!(c.buses_reopened.is_empty());
}

#[test]
fn tokens_are_counted_and_need_no_listener() {
    let c = changed(
        "[modbus_tcp]",
        "[[http.token]]\nname = \"scada\"\nrole = \"viewer\"\nsha256 = \"1111111111111111111111111111111111111111111111111111111111111111\"\n[modbus_tcp]",
    );
    assert_eq!(c.tokens_changed, 1);
    assert!(c.faces_restarted.is_empty(), "{c:?}");
    let c = changed("role = \"operator\"", "role = \"admin\"");
    assert_eq!(c.tokens_changed, 1);
    assert_eq!(c.lines(), vec!["tokens changed: 1"]);
}

#[test]
fn the_last_token_gone_reopens_http_on_loopback() {
    let c = diff(
        &parse(BASE),
        &parse(&BASE.replace(
            "[[http.token]]\nname = \"panel\"\nrole = \"operator\"\nsha256 = \"0000000000000000000000000000000000000000000000000000000000000000\"\n",
            "",
        )),
    );
    assert_eq!(c.tokens_changed, 1);
    assert_eq!(c.faces_restarted, vec![Face::Http]);
}

#[test]
fn listen_addresses_reopen_their_listener() {
    let c = changed("127.0.0.1:8080", "127.0.0.1:8081");
    assert_eq!(c.faces_restarted, vec![Face::Http]);
    assert_eq!(c.lines(), vec!["restarted: HTTP API listener"]);
    let c = changed("127.0.0.1:5020", "127.0.0.1:5021");
    assert_eq!(c.faces_restarted, vec![Face::ModbusTcp]);
    assert!(c.buses_reopened.is_empty());
}

#[test]
fn safety_clients_scope_and_log() {
    let c = changed("[http]", "[safety]\nlease_max_ms = 20000\n[http]");
    assert_eq!(c.sections, vec!["[safety]"]);
    assert!(c.buses_reopened.is_empty());
    let c = changed(
        "listen = \"127.0.0.1:5020\"",
        "listen = \"127.0.0.1:5020\"\nread_only = true",
    );
    assert_eq!(c.sections, vec!["[modbus_tcp] clients and units"]);
    assert_eq!(
        c.faces_restarted,
        vec![],
        "no Modbus/TCP Security listener to follow it"
    );
    let c = changed("[http]", "[scope]\nmax_samples = 1000\n[http]");
    assert_eq!(c.sections, vec!["[scope]"]);
    assert_eq!(
        c.buses_reopened.len(),
        2,
        "the scope's limits size every bus's slot"
    );
    let c = changed("[http]", "[log]\nformat = \"json\"\n[http]");
    assert_eq!(c.at_restart, vec!["[log]"]);
}

/// The reference configuration (`config/drivegate.toml`), every key at
/// its default.
fn reference() -> Config {
    parse(include_str!("../../../config/drivegate.toml"))
}

/// `change` applied to the reference configuration.
fn changed_by(change: impl FnOnce(&mut Config)) -> Changes {
    let old = reference();
    let mut new = old.clone();
    change(&mut new);
    assert_ne!(old, new, "the change changes nothing");
    diff(&old, &new)
}

/// The reference configuration with `text` added at its end.
fn with(text: &str) -> Config {
    parse(&format!(
        "{}\n{text}",
        include_str!("../../../config/drivegate.toml")
    ))
}

/// A change of the reference configuration: what is changed, the change,
/// and what the diff must say of it.
type Case = (
    &'static str,
    Box<dyn FnOnce(&mut Config)>,
    Vec<&'static str>,
);

/// `[http]` and its tokens: the listener restarts; tokens apply at once.
fn http_changes() -> Vec<Case> {
    use std::time::Duration;
    vec![
        (
            "[http] listen",
            Box::new(|c| c.http.listen.set_port(18080)),
            vec!["restarted: HTTP API listener"],
        ),
        (
            "[http] a limit",
            Box::new(|c| c.http.idle_timeout += Duration::from_secs(1)),
            vec!["restarted: HTTP API listener"],
        ),
        (
            "[http] allowed_hosts",
            Box::new(|c| c.http.allowed_hosts.push("gateway.plant".into())),
            vec!["restarted: HTTP API listener"],
        ),
        (
            "[[http.token]]",
            Box::new(|c| {
                c.http.tokens = with(
                    "[[http.token]]\nname = \"panel\"\nrole = \"viewer\"\nsha256 = \"2222222222222222222222222222222222222222222222222222222222222222\"",
                )
                .http
                .tokens;
            }),
            vec!["tokens changed: 1"],
        ),
    ]
}

/// `[modbus_tcp]`: the listener and its limits restart it; what its
/// clients may do applies at once.
fn modbus_tcp_changes() -> Vec<Case> {
    vec![
        (
            "[modbus_tcp] listen",
            Box::new(|c| c.modbus_tcp.listen.set_port(15020)),
            vec!["restarted: Modbus TCP listener"],
        ),
        (
            "[modbus_tcp] enabled",
            Box::new(|c| c.modbus_tcp.enabled = false),
            vec!["restarted: Modbus TCP listener"],
        ),
        (
            "[modbus_tcp] max_pipelined",
            Box::new(|c| c.modbus_tcp.max_pipelined += 1),
            vec!["restarted: Modbus TCP listener"],
        ),
        (
            "[modbus_tcp] max_connections_per_address",
            Box::new(|c| {
                let three = crate::config::modbus_tcp::ConnectionCount(3);
                c.modbus_tcp.max_connections_per_address = Some(toml::Spanned::new(0..0, three));
            }),
            vec!["restarted: Modbus TCP listener"],
        ),
        (
            "[modbus_tcp] read_only",
            Box::new(|c| c.modbus_tcp.read_only = !c.modbus_tcp.read_only),
            vec!["applied: [modbus_tcp] clients and units"],
        ),
        (
            "[modbus_tcp] allowed_networks",
            Box::new(|c| c.modbus_tcp.allowed_networks = Some(Vec::new())),
            vec!["applied: [modbus_tcp] clients and units"],
        ),
        (
            "[modbus_tcp] raw_functions",
            Box::new(|c| {
                let vendor = crate::config::modbus_tcp::RawFunction::try_from(0x41);
                c.modbus_tcp.raw_functions = vendor
                    .map(|f| vec![toml::Spanned::new(0..0, f)])
                    .unwrap_or_default();
            }),
            vec!["applied: [modbus_tcp] clients and units"],
        ),
        (
            "[modbus_tcp] broadcast_reply",
            Box::new(|c| c.modbus_tcp.broadcast_reply = !c.modbus_tcp.broadcast_reply),
            vec!["applied: [modbus_tcp] clients and units"],
        ),
        (
            "[[modbus_tcp.clients]]",
            Box::new(|c| {
                c.modbus_tcp.clients.pop();
            }),
            vec!["applied: [modbus_tcp] clients and units"],
        ),
        (
            "[[modbus_tcp.unit_map]]",
            Box::new(|c| {
                c.modbus_tcp.unit_map.pop();
            }),
            vec!["applied: [modbus_tcp] clients and units"],
        ),
    ]
}

/// `[mqtt]` restarts its face; `[log]` waits for the next start.
fn mqtt_and_log_changes() -> Vec<Case> {
    vec![
        (
            "[mqtt] added",
            Box::new(|c| {
                c.mqtt = with("[mqtt]\nbroker = \"mqtt://127.0.0.1:1883\"").mqtt;
            }),
            vec!["restarted: MQTT face"],
        ),
        (
            "[log]",
            Box::new(|c| c.log.level = "debug".into()),
            vec!["applies at the next start: [log]"],
        ),
    ]
}

/// `[safety]`: the lease settings and stops apply at once; the state
/// directory and the alarm list at the next start.
fn safety_changes() -> Vec<Case> {
    vec![
        (
            "[safety] on_shutdown",
            Box::new(|c| c.safety.on_shutdown = crate::config::StopAction::Brake),
            vec!["applied: [safety]"],
        ),
        (
            "[safety] lease_max_ms",
            Box::new(|c| c.safety.lease_max_ms += 1),
            vec!["applied: [safety]"],
        ),
        (
            "[safety] alarms_kept",
            Box::new(|c| c.safety.alarms_kept += 1),
            vec!["applies at the next start: [safety] state_dir, on_unknown_state and alarms_kept"],
        ),
        (
            "[safety] state_dir",
            Box::new(|c| c.safety.state_dir = Some("/var/lib/elsewhere".into())),
            vec!["applies at the next start: [safety] state_dir, on_unknown_state and alarms_kept"],
        ),
    ]
}

/// `[monitor]` and `[scope]` apply at once; `[history]` at the next start.
fn observers_changes() -> Vec<Case> {
    vec![
        (
            "[monitor]",
            Box::new(|c| c.monitor.ring_frames += 1),
            vec!["applied: [monitor]"],
        ),
        (
            "[scope]",
            Box::new(|c| c.scope.max_samples += 1),
            vec!["applied: [scope]"],
        ),
        (
            "[history]",
            Box::new(|c| c.history.minutes = 30),
            vec!["applies at the next start: [history]"],
        ),
    ]
}

/// `[[bus]]` and `[[bus.drive]]`: buses reopened, added, drives removed.
fn buses_changes() -> Vec<Case> {
    vec![
        (
            "[[bus]] baud",
            Box::new(|c| c.buses[0].baud = 57600),
            vec!["bus "],
        ),
        (
            "[[bus]] added",
            Box::new(|c| {
                c.buses = with("[[bus]]\nname = \"another\"\nport = \"sim\"").buses;
            }),
            vec!["buses added: another"],
        ),
        (
            "[[bus.drive]]",
            Box::new(|c| {
                c.buses[0].drives.pop();
            }),
            vec!["drives removed: "],
        ),
    ]
}

#[test]
fn a_change_of_any_section_is_applied_or_said_to_wait_for_the_next_start() {
    let cases = [
        http_changes(),
        modbus_tcp_changes(),
        mqtt_and_log_changes(),
        safety_changes(),
        observers_changes(),
        buses_changes(),
    ];
    for (what, change, says) in cases.into_iter().flatten() {
        let c = changed_by(change);
        let lines = c.lines();
        for said in says {
            assert!(
                lines.iter().any(|l| l.starts_with(said)),
                "a change of {what} is not reported as {said:?}: {lines:?}"
            );
        }
    }
}

#[test]
fn opcua_changes_restart_only_its_listener() {
    // The reference shows [opcua]; without it, no OPC UA.
    let mut old = reference();
    old.opcua = None;
    let new = reference();
    assert_eq!(diff(&old, &new).faces_restarted, vec![Face::OpcUa]);
    assert_eq!(diff(&new, &old).faces_restarted, vec![Face::OpcUa]);
    assert_eq!(diff(&old, &new).lines(), vec!["restarted: OPC UA listener"]);
    let mut longer = new.clone();
    if let Some(o) = longer.opcua.as_mut() {
        o.session_timeout_max_ms += 1000;
    }
    assert_eq!(diff(&new, &longer).faces_restarted, vec![Face::OpcUa]);
    // Its certificates are in the state directory.
    let mut moved = new.clone();
    moved.safety.state_dir = Some("/var/lib/elsewhere".into());
    assert!(diff(&new, &moved).faces_restarted.contains(&Face::OpcUa));
    assert!(
        !diff(&old, &{
            let mut o = old.clone();
            o.safety.state_dir = Some("/var/lib/elsewhere".into());
            o
        })
        .faces_restarted
        .contains(&Face::OpcUa)
    );
}

#[test]
fn tls_and_mqtt_changes_restart_only_their_face() {
    let tls = "[modbus_tcp.tls]\nlisten = \"127.0.0.1:802\"\ncert = \"/x/gw.pem\"\nkey = \"/x/gw.key\"\nclient_ca = \"/x/ca.pem\"\n";
    let (old, new) = (reference(), with(tls));
    assert_eq!(diff(&old, &new).faces_restarted, vec![Face::ModbusTls]);
    assert_eq!(diff(&new, &old).faces_restarted, vec![Face::ModbusTls]);
    // The plain listener's limits are the secure one's too.
    let mut limits = new.clone();
    limits.modbus_tcp.max_connections = Some(crate::config::modbus_tcp::ConnectionCount(100));
    assert_eq!(
        diff(&new, &limits).faces_restarted,
        vec![Face::ModbusTcp, Face::ModbusTls]
    );
    let mqtt = "[mqtt]\nbroker = \"mqtt://127.0.0.1:1883\"\n";
    // Without the reference's [opcua], whose certificates are in the
    // state directory too.
    let plain = |mut c: Config| {
        c.opcua = None;
        c
    };
    let (a, b) = (
        plain(with(mqtt)),
        plain(with(&mqtt.replace("1883", "1884"))),
    );
    let c = diff(&a, &b);
    assert_eq!(c.faces_restarted, vec![Face::Mqtt]);
    assert_eq!(c.lines(), vec!["restarted: MQTT face"]);
    // Its store is in the state directory.
    let mut moved = a.clone();
    moved.safety.state_dir = Some("/var/lib/elsewhere".into());
    assert_eq!(diff(&a, &moved).faces_restarted, vec![Face::Mqtt]);
    assert_eq!(
        diff(&a, &plain(reference())).faces_restarted,
        vec![Face::Mqtt]
    );
}
