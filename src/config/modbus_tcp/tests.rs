//! `[modbus_tcp]` parsed and checked: values, spans of errors, the notices.

use super::*;
use crate::config::Config;

const TWO_BUSES: &str = r#"
[[bus]]
name = "A"
port = "sim"
[[bus.drive]]
unit = 1
name = "a1"
[[bus]]
name = "B"
port = "sim"
[[bus.drive]]
unit = 1
name = "b1"
"#;

fn parse(modbus_tcp: &str) -> Result<Config, String> {
    Config::parse(
        &format!("[modbus_tcp]\n{modbus_tcp}\n{TWO_BUSES}"),
        "t.toml",
    )
    .map_err(|e| e.to_string())
}

#[test]
fn the_reference_config_documents_working_examples() {
    let text = include_str!("../../../config/drivegate.toml")
        .replace("# [[modbus_tcp.polled_copy]]", "[[modbus_tcp.polled_copy]]")
        .replace(
            "# bus = \"line1\"\n# max_age_ms",
            "bus = \"line1\"\nmax_age_ms",
        )
        // The first of each: the [mqtt] section shows these keys too.
        .replacen("# comm_loss_ms = 500", "comm_loss_ms = 500", 1)
        .replacen(
            "# comm_loss_action = \"zero-speed\"",
            "comm_loss_action = \"zero-speed\"",
            1,
        );
    let c = Config::parse(&text, "drivegate.toml").unwrap();
    let tcp = &c.modbus_tcp;
    assert_eq!(tcp.allowed_networks, None);
    assert_eq!(tcp.allowed(), default_allowed_networks());
    assert_eq!(tcp.unit_map[1].bus_unit(101), Some(1));
    assert_eq!(tcp.polled_copy[0].max_age(), Duration::from_millis(250));
    assert_eq!(tcp.clients[0].role(), Role::Operator);
    assert_eq!(
        tcp.clients[0].comm_loss(),
        Some(CommLossConfig {
            after: Duration::from_millis(500),
            action: StopAction::ZeroSpeed
        })
    );
    assert_eq!(tcp.clients[1].role(), Role::Viewer);
    let mut defaults = tcp.clone();
    defaults.unit_map.clear();
    defaults.polled_copy.clear();
    defaults.clients.clear();
    assert_eq!(defaults, ModbusTcpConfig::default());
}

#[test]
fn defaults() {
    let c = ModbusTcpConfig::default();
    assert_eq!(c.max_connections, None);
    // Twice the drives plus 32, at least 64.
    assert_eq!(c.connection_limit(0), 64);
    assert_eq!(c.connection_limit(16), 64);
    assert_eq!(c.connection_limit(32), 96);
    assert_eq!(c.connection_limit(247), 526);
    assert_eq!(c.idle_timeout(), Duration::from_secs(60));
    assert!(!c.read_only && !c.broadcast_reply);
    assert!(c.unit_map.is_empty() && c.polled_copy.is_empty() && c.clients.is_empty());
    assert_eq!(c.allowed_networks, None);
    assert_eq!(
        c.allowed()
            .iter()
            .map(|n| n.to_string())
            .collect::<Vec<_>>(),
        ["127.0.0.0/8", "::1/128"],
        "loopback only"
    );
    assert_eq!(c.per_address_limit(), None, "no hard cap: fair shares");
    assert!(c.raw_functions.is_empty());
}

#[test]
fn the_per_address_cap_is_within_max_connections() {
    let c = parse("max_connections = 6").unwrap();
    assert_eq!(c.modbus_tcp.per_address_limit(), None);
    assert_eq!(
        c.modbus_tcp.connection_limit(100),
        6,
        "as set, whatever the drives"
    );
    let c = parse("max_connections = 2\nmax_connections_per_address = 2").unwrap();
    assert_eq!(c.modbus_tcp.per_address_limit(), Some(2));
    // Without max_connections, a cap within the range is taken as it is.
    let c = parse("max_connections_per_address = 300").unwrap();
    assert_eq!(c.modbus_tcp.per_address_limit(), Some(300));
    let e = parse("max_connections = 8\nmax_connections_per_address = 9").unwrap_err();
    assert!(
        e.starts_with("t.toml:3:31:")
            && e.contains(
                "max_connections_per_address = 9 is out of range: valid 1 to 8 (max_connections)"
            ),
        "{e}"
    );
    let e = parse("max_connections_per_address = 0").unwrap_err();
    assert!(e.contains("0 is out of range: valid 1 to 4096"), "{e}");
}

#[test]
fn raw_functions_lists_only_codes_the_core_cannot_decode() {
    let c = parse("raw_functions = [0x05, 0x0F, 0x41, 8, 0x2B]").unwrap();
    let codes: Vec<u8> = c
        .modbus_tcp
        .raw_functions
        .iter()
        .map(|f| f.get_ref().code())
        .collect();
    assert_eq!(codes, [0x05, 0x0F, 0x41, 0x08, 0x2B]);
    let e = parse("raw_functions = [0x41, 0x06]").unwrap_err();
    assert!(
        e.starts_with("t.toml:2:24:")
            && e.contains("lists 0x06 (Write Single Register): a register write, which the control core decodes and always checks"),
        "{e}"
    );
    let e = parse("raw_functions = [0x03]").unwrap_err();
    assert!(e.contains("0x03 (Read Holding Registers): a read"), "{e}");
    for bad in ["0", "128", "-1"] {
        let e = parse(&format!("raw_functions = [{bad}]")).unwrap_err();
        assert!(
            e.contains(&format!(
                "function code {bad} is out of range: valid 1 to 127"
            )),
            "{e}"
        );
    }
}

#[test]
fn plain_admin_networks_and_the_old_default_are_noticed() {
    let warnings = |text: &str| -> Vec<String> {
        let c = parse(text).unwrap();
        c.modbus_tcp
            .notices(c.modbus_tcp.listen)
            .into_iter()
            .map(|(_, t)| t)
            .collect()
    };
    // On loopback nothing is said: nobody else reaches the listener.
    assert!(warnings("allowed_networks = [\"10.0.0.0/8\"]").is_empty());
    let w =
        warnings("listen = \"0.0.0.0:502\"\nallowed_networks = [\"127.0.0.1/32\", \"10.0.0.0/8\"]");
    assert_eq!(w.len(), 1, "{w:?}");
    assert!(
        w[0].contains("allowed_networks gives 10.0.0.0/8 the admin role over plain Modbus TCP")
            && w[0].contains("Modbus/TCP Security"),
        "{w:?}"
    );
    let w = warnings(
        "listen = \"0.0.0.0:502\"\nallowed_networks = []\n[[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"admin\"\n[[modbus_tcp.clients]]\nnetwork = \"10.2.0.0/16\"\nrole = \"operator\"",
    );
    assert_eq!(w.len(), 1, "{w:?}");
    assert!(
        w[0].contains("[[modbus_tcp.clients]] gives 10.1.0.0/16 the admin role"),
        "{w:?}"
    );
    // read_only: nobody is admin.
    assert!(
        warnings("listen = \"0.0.0.0:502\"\nallowed_networks = [\"10.0.0.0/8\"]\nread_only = true")
            .is_empty()
    );
    // A file that relied on the private ranges being admitted.
    let c = parse("listen = \"0.0.0.0:502\"").unwrap();
    let notices = c.modbus_tcp.notices(c.modbus_tcp.listen);
    assert_eq!(notices.len(), 1);
    let (warning, text) = &notices[0];
    assert!(*warning);
    assert!(
        text.contains("listens on 0.0.0.0:502 but admits loopback only")
            && text.contains("no longer defaults to the private networks (10.0.0.0/8")
            && text.contains("[[modbus_tcp.clients]]"),
        "{text}"
    );
    let c = parse("listen = \"0.0.0.0:502\"\n[[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"operator\"").unwrap();
    let notices = c.modbus_tcp.notices(c.modbus_tcp.listen);
    assert_eq!(notices.len(), 1);
    assert!(
        !notices[0].0,
        "a file with a client network works as written"
    );
    assert!(
        notices[0]
            .1
            .contains("admits loopback and 10.1.0.0/16 (operator)"),
        "{}",
        notices[0].1
    );
}

#[test]
fn unit_map_ranges_and_offsets() {
    let c = parse(
        r#"
[[modbus_tcp.unit_map]]
units = "1-32"
bus = "A"
[[modbus_tcp.unit_map]]
units = "101-132"
bus = "B"
bus_units = "1-32"
[[modbus_tcp.unit_map]]
units = 200
bus = "B"
bus_units = "40"
"#,
    )
    .unwrap();
    let map = &c.modbus_tcp.unit_map;
    assert_eq!(map[0].bus_unit(1), Some(1));
    assert_eq!(map[0].bus_unit(32), Some(32));
    assert_eq!(map[0].bus_unit(33), None);
    assert_eq!(map[1].bus_unit(101), Some(1));
    assert_eq!(map[1].bus_unit(132), Some(32));
    assert_eq!(map[2].bus_unit(200), Some(40));
}

#[test]
fn bad_ranges_name_the_valid_range_and_position() {
    let e = parse("[[modbus_tcp.unit_map]]\nunits = \"0-4\"\nbus = \"A\"").unwrap_err();
    assert!(
        e.contains("t.toml:3:9") && e.contains("valid 1 to 255"),
        "{e}"
    );
    let e = parse("[[modbus_tcp.unit_map]]\nunits = \"9-3\"\nbus = \"A\"").unwrap_err();
    assert!(e.contains("runs backwards"), "{e}");
    let e = parse("[[modbus_tcp.unit_map]]\nunits = \"one\"\nbus = \"A\"").unwrap_err();
    assert!(e.contains("is not a unit range"), "{e}");
    let e = parse("max_connections = 0").unwrap_err();
    assert!(
        e.contains("t.toml:2:19") && e.contains("valid 1 to 4096"),
        "{e}"
    );
    let e = parse("allowed_networks = [\"10.0.0.0/33\"]").unwrap_err();
    assert!(e.contains("t.toml:2:"), "{e}");
}

#[test]
fn client_networks_carry_a_role_and_the_override() {
    let c = parse(
        "[[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"operator\"\n[[modbus_tcp.clients]]\nnetwork = \"10.1.9.0/24\"\nrole = \"admin\"\nallow_saves_while_moving = true",
    )
    .unwrap();
    let clients = &c.modbus_tcp.clients;
    assert_eq!(clients[0].role(), Role::Operator);
    assert!(!clients[0].allow_saves_while_moving);
    assert!(clients[1].allow_saves_while_moving);
    let e =
        parse("[[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"boss\"").unwrap_err();
    assert!(
        e.contains("t.toml:4:8") && e.contains("unknown variant `boss`"),
        "{e}"
    );
    let e = parse("[[modbus_tcp.clients]]\nrole = \"viewer\"").unwrap_err();
    assert!(e.contains("missing field `network`"), "{e}");
    // read_only makes everybody a viewer: a higher role contradicts it.
    let e = parse(
        "read_only = true\n[[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"operator\"",
    )
    .unwrap_err();
    assert!(
        e.contains("t.toml:5:8") && e.contains("read_only = true makes every client a viewer"),
        "{e}"
    );
    parse("read_only = true\n[[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"viewer\"")
        .unwrap();
}

#[test]
fn client_networks_may_have_a_comm_loss_time_and_action() {
    let c = parse(
        "[[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"operator\"\ncomm_loss_ms = 500\n[[modbus_tcp.clients]]\nnetwork = \"10.2.0.0/16\"\nrole = \"operator\"\ncomm_loss_ms = 20\ncomm_loss_action = \"brake\"\n[[modbus_tcp.clients]]\nnetwork = \"10.3.0.0/16\"\nrole = \"operator\"\ncomm_loss_ms = 60000\ncomm_loss_action = \"none\"\n[[modbus_tcp.clients]]\nnetwork = \"10.4.0.0/16\"\nrole = \"operator\"",
    )
    .unwrap();
    let loss: Vec<Option<CommLossConfig>> =
        c.modbus_tcp.clients.iter().map(|c| c.comm_loss()).collect();
    let ms = Duration::from_millis;
    assert_eq!(
        loss,
        [
            Some(CommLossConfig {
                after: ms(500),
                action: StopAction::ZeroSpeed
            }),
            Some(CommLossConfig {
                after: ms(20),
                action: StopAction::Brake
            }),
            Some(CommLossConfig {
                after: ms(60_000),
                action: StopAction::None
            }),
            None,
        ],
        "zero-speed by default; off without a time"
    );
    for bad in ["19", "60001", "0", "-5"] {
        let e = parse(&format!(
            "[[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"operator\"\ncomm_loss_ms = {bad}"
        ))
        .unwrap_err();
        assert!(
            e.contains("t.toml:5:16")
                && e.contains(&format!(
                    "comm_loss_ms = {bad} is out of range: valid 20 to 60000 ms"
                )),
            "{e}"
        );
    }
    let e = parse(
        "[[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"operator\"\ncomm_loss_action = \"stop\"",
    )
    .unwrap_err();
    assert!(
        e.contains("t.toml:5:20") && e.contains("unknown variant `stop`"),
        "{e}"
    );
    let e = parse(
        "[[modbus_tcp.clients]]\nnetwork = \"10.1.0.0/16\"\nrole = \"operator\"\ncomm_loss_action = \"brake\"",
    )
    .unwrap_err();
    assert!(
        e.starts_with("t.toml:5:20:") && e.contains("has comm_loss_action but no comm_loss_ms"),
        "{e}"
    );
}

#[test]
fn errors_point_at_the_value_to_fix() {
    // line 1 is [modbus_tcp]; the bus name is on line 4, column 7.
    let e = parse("[[modbus_tcp.unit_map]]\nunits = \"1-4\"\nbus = \"C\"").unwrap_err();
    assert!(e.starts_with("t.toml:4:7:"), "{e}");
    let e = parse("[[modbus_tcp.unit_map]]\nunits = \"1-4\"\nbus = \"A\"\nbus_units = \"1-3\"")
        .unwrap_err();
    assert!(e.starts_with("t.toml:5:13:"), "{e}");
    let e = parse(
        "[[modbus_tcp.unit_map]]\nunits = \"1-10\"\nbus = \"A\"\n[[modbus_tcp.unit_map]]\nunits = \"10-20\"\nbus = \"B\"",
    )
    .unwrap_err();
    assert!(e.starts_with("t.toml:6:9:"), "{e}");
    let e = parse(
        "[[modbus_tcp.polled_copy]]\nbus = \"A\"\nmax_age_ms = 100\n[[modbus_tcp.polled_copy]]\nbus = \"A\"\nmax_age_ms = 50",
    )
    .unwrap_err();
    assert!(e.starts_with("t.toml:6:7:"), "{e}");
}

#[test]
fn the_map_is_checked_against_the_buses() {
    let e = parse("[[modbus_tcp.unit_map]]\nunits = \"1-4\"\nbus = \"C\"").unwrap_err();
    assert!(
        e.contains("unit_map entry 1 (units 1-4) names bus \"C\", which is not configured (buses: \"A\", \"B\")"),
        "{e}"
    );
    let e = parse("[[modbus_tcp.unit_map]]\nunits = \"1-4\"\nbus = \"A\"\nbus_units = \"1-3\"")
        .unwrap_err();
    assert!(e.contains("has 3 units but units 1-4 has 4"), "{e}");
    let e = parse(
        "[[modbus_tcp.unit_map]]\nunits = \"1-10\"\nbus = \"A\"\n[[modbus_tcp.unit_map]]\nunits = \"10-20\"\nbus = \"B\"",
    )
    .unwrap_err();
    assert!(
        e.contains("unit_map entry 2 (units 10-20) overlaps unit_map entry 1 (units 1-10)"),
        "{e}"
    );
    let e = parse("[[modbus_tcp.polled_copy]]\nbus = \"X\"\nmax_age_ms = 100").unwrap_err();
    assert!(e.contains("polled_copy entry 1 names bus \"X\""), "{e}");
    let e = parse(
        "[[modbus_tcp.polled_copy]]\nbus = \"A\"\nmax_age_ms = 100\n[[modbus_tcp.polled_copy]]\nbus = \"A\"\nmax_age_ms = 50",
    )
    .unwrap_err();
    assert!(e.contains("lists bus \"A\" twice"), "{e}");
    let e = parse("[[modbus_tcp.polled_copy]]\nbus = \"A\"\nmax_age_ms = 0").unwrap_err();
    assert!(e.contains("valid 1 to 60000"), "{e}");
}
