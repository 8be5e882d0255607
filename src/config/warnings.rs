//! What a valid configuration holds that is probably a mistake, or a
//! risk taken on purpose, said without refusing it: a bus at a baud rate
//! that no adapter or drive commonly uses (`11520` typed for `115200`),
//! where the drives would never answer and nothing else would say why;
//! MQTT commands taken from any client of the broker
//! (`unauthenticated_commands = true`).
//!
//! `drivegate check-config` prints these, `serve` and every reload log
//! them; the file is still taken (an unusual rate may be meant).

use serde::Deserialize;
use toml::Spanned;

use super::Config;
use super::error::line_column;

/// The rates serial adapters and RS-485 devices commonly use. The drives
/// of the manual speak 115200 (section 1.1).
pub const STANDARD_BAUDS: [u32; 11] = [
    1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400, 460800, 921600,
];

/// The warnings for `text` (already parsed and valid, as `config`), each
/// as `origin:line:column: what`.
pub fn warnings(config: &Config, text: &str, origin: &str) -> Vec<String> {
    // Only what the warnings look at, with positions; the rest of the
    // file was checked by the parser.
    #[derive(Deserialize)]
    struct File {
        #[serde(default)]
        bus: Vec<Bus>,
        mqtt: Option<Mqtt>,
    }
    #[derive(Deserialize)]
    struct Bus {
        name: Option<String>,
        baud: Option<Spanned<i64>>,
    }
    #[derive(Deserialize)]
    struct Mqtt {
        unauthenticated_commands: Option<Spanned<bool>>,
    }
    let Ok(file) = toml::from_str::<File>(text) else {
        return Vec::new();
    };
    let at = |span: std::ops::Range<usize>| {
        let (line, column) = line_column(text, span.start);
        format!("{origin}:{line}:{column}")
    };
    let mut out = Vec::new();
    for bus in &file.bus {
        let Some(baud) = &bus.baud else { continue };
        let rate = *baud.get_ref();
        if u32::try_from(rate).is_ok_and(|r| STANDARD_BAUDS.contains(&r)) {
            continue;
        }
        let name = bus.name.as_deref().unwrap_or("?");
        out.push(format!(
            "{}: bus \"{name}\": baud = {rate} is not a standard rate{}: \
             a drive at another rate never answers. The drives speak 115200; the standard \
             rates are {}. `drivegate probe --port PORT --try-bauds` finds the rate the \
             drives answer at",
            at(baud.span()),
            did_you_mean(rate),
            STANDARD_BAUDS.map(|b| b.to_string()).join(", "),
        ));
    }
    if let Some(warning) = config
        .mqtt
        .as_ref()
        .and_then(|m| m.unauthenticated_warning())
        && let Some(key) = file.mqtt.and_then(|m| m.unauthenticated_commands)
    {
        out.push(format!("{}: {warning}", at(key.span())));
    }
    out
}

/// ", did you mean 115200?" for a rate one slip away from a standard one.
fn did_you_mean(rate: i64) -> String {
    let rates = STANDARD_BAUDS.map(|b| b.to_string());
    crate::suggest::closest(&rate.to_string(), rates.iter().map(String::as_str))
        .map(|r| format!(" (did you mean {r}?)"))
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn warnings(text: &str, origin: &str) -> Vec<String> {
        let config = Config::parse(text, origin).unwrap();
        super::warnings(&config, text, origin)
    }

    #[test]
    fn a_typo_in_the_baud_rate_is_named_with_the_rate_meant() {
        let text = "[[bus]]\nname = \"line1\"\nport = \"sim\"\nbaud = 11520\n";
        let w = warnings(text, "plant.toml");
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].starts_with(
                "plant.toml:4:8: bus \"line1\": baud = 11520 is not a standard rate (did you mean 115200?)"
            ),
            "{w:?}"
        );
        assert!(
            w[0].contains("1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200, 230400")
                && w[0].contains("--try-bauds"),
            "{w:?}"
        );
        // Far from every standard rate: no guess, still the list.
        let w = warnings("[[bus]]\nname = \"x\"\nport = \"sim\"\nbaud = 31250\n", "f");
        assert!(
            w[0].contains("31250 is not a standard rate: a drive"),
            "{w:?}"
        );
    }

    #[test]
    fn standard_rates_and_the_default_are_no_warning() {
        for baud in ["", "baud = 115200\n", "baud = 9600\n", "baud = 921600\n"] {
            let text = format!("[[bus]]\nname = \"line1\"\nport = \"sim\"\n{baud}");
            assert!(warnings(&text, "f").is_empty(), "{baud}");
        }
    }

    #[test]
    fn mqtt_commands_from_any_client_are_a_warning_where_they_take_effect() {
        let mqtt = "[mqtt]\nbroker = \"mqtt://10.0.0.5:1883\"\n";
        let text = format!("{mqtt}commands = \"operator\"\nunauthenticated_commands = true\n");
        let w = warnings(&text, "plant.toml");
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].starts_with(
                "plant.toml:4:28: [mqtt] unauthenticated_commands = true: commands are taken \
                 from any client of the broker"
            ) && w[0].contains("\"unauthenticated broker 10.0.0.5:1883\"")
                && w[0].contains("username and password_file"),
            "{w:?}"
        );
        // Without commands, or with a login, the key changes nothing.
        for keys in [
            "unauthenticated_commands = true\n",
            "commands = \"operator\"\nunauthenticated_commands = true\nusername = \"gw1\"\n\
             password_file = \"/etc/drivegate/mqtt-password\"\n",
        ] {
            assert!(warnings(&format!("{mqtt}{keys}"), "f").is_empty(), "{keys}");
        }
    }
}
