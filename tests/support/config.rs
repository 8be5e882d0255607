//! The daemon's configuration file, built in the words of the plant: which
//! buses, which drives on them, which faces listen and with what keys.
//! [`ConfigBuilder::toml`] renders the TOML the daemon reads, so a test
//! states only what differs from a quiet plant on loopback:
//!
//! ```ignore
//! let toml = ConfigBuilder::new()
//!     .bus("line", |b| b.drive(1, "belt").drive(2, "lift"))
//!     .http_token("scada", "operator", OPERATOR)
//!     .modbus_tcp("read_only = true")
//!     .section("safety", "on_shutdown = \"none\"")
//!     .toml();
//! ```
//!
//! Tests of the file format itself (unknown keys, wrong types, a bad
//! value's message) keep their TOML literal: there the text is the subject.

use crate::support::WIRE_TIMING;

/// A daemon configuration under construction. Both faces listen on
/// loopback ports the system chooses; nothing else is set until a test
/// says so, and the daemon's defaults apply.
#[derive(Debug, Clone)]
pub struct ConfigBuilder {
    http: Vec<String>,
    tokens: Vec<String>,
    /// `None`: the Modbus TCP face is off.
    modbus_tcp: Option<Vec<String>>,
    /// `[[modbus_tcp.unit_map]]` and the like, after the `[modbus_tcp]` keys.
    modbus_tcp_tables: Vec<String>,
    /// `[name]` sections in the order first named, with their key lines.
    sections: Vec<(String, Vec<String>)>,
    buses: Vec<BusBuilder>,
    /// Whole tables a test writes itself, after everything else.
    tables: String,
}

impl Default for ConfigBuilder {
    fn default() -> Self {
        Self::new()
    }
}

impl ConfigBuilder {
    /// HTTP and Modbus TCP on `127.0.0.1:0`, no buses yet.
    pub fn new() -> Self {
        ConfigBuilder {
            http: vec!["listen = \"127.0.0.1:0\"".into()],
            tokens: Vec::new(),
            modbus_tcp: Some(vec!["listen = \"127.0.0.1:0\"".into()]),
            modbus_tcp_tables: Vec::new(),
            sections: Vec::new(),
            buses: Vec::new(),
            tables: String::new(),
        }
    }

    /// The plant of [`FOUR_DRIVES`](crate::support::FOUR_DRIVES): one
    /// simulated bus `sim` (seed 7) with the conveyor (unit 1, gear 3.75),
    /// the lift (2, 10.0), the turntable (3, 3.75) and the feeder (4, 1.0).
    pub fn four_drives() -> Self {
        let preset = Self::new().bus("sim", |b| {
            b.sim("seed = 7")
                .geared_drive(1, "conveyor", 3.75)
                .geared_drive(2, "lift", 10.0)
                .geared_drive(3, "turntable", 3.75)
                .geared_drive(4, "feeder", 1.0)
        });
        // The constant and the preset are one plant: a test that uses
        // either sees the same drives.
        let parse = |text: &str| text.parse::<toml::Table>().expect("valid TOML");
        assert_eq!(
            parse(&preset.toml()),
            parse(crate::support::FOUR_DRIVES),
            "ConfigBuilder::four_drives() and FOUR_DRIVES differ"
        );
        preset
    }

    /// Key lines added to `[http]` (e.g. `"max_connections = 3"`).
    pub fn http(mut self, keys: &str) -> Self {
        push_lines(&mut self.http, keys);
        self
    }

    /// An `[[http.token]]` named `name` with `role`, for the bearer token
    /// `secret` (the file holds only its SHA-256).
    pub fn http_token(mut self, name: &str, role: &str, secret: &str) -> Self {
        self.tokens.push(format!(
            "[[http.token]]\nname = \"{name}\"\nrole = \"{role}\"\nsha256 = \"{}\"\n",
            sha256_hex(secret)
        ));
        self
    }

    /// HTTP listening on `addr` instead of `127.0.0.1:0`.
    pub fn http_listen(mut self, addr: &str) -> Self {
        self.http.retain(|l| key_of(l) != "listen");
        self.http.insert(0, format!("listen = \"{addr}\""));
        self
    }

    /// Modbus TCP listening on `addr` instead of `127.0.0.1:0` (turning the
    /// face on if it was off).
    pub fn modbus_tcp_listen(mut self, addr: &str) -> Self {
        let lines = self.modbus_tcp.get_or_insert_with(Vec::new);
        lines.retain(|l| key_of(l) != "listen");
        lines.insert(0, format!("listen = \"{addr}\""));
        self
    }

    /// Key lines added to `[modbus_tcp]` (turning the face on if it was off).
    pub fn modbus_tcp(mut self, keys: &str) -> Self {
        let lines = self
            .modbus_tcp
            .get_or_insert_with(|| vec!["listen = \"127.0.0.1:0\"".into()]);
        push_lines(lines, keys);
        self
    }

    /// The Modbus TCP face off (`enabled = false`), for tests that reach
    /// the bus another way.
    pub fn modbus_tcp_off(mut self) -> Self {
        self.modbus_tcp = None;
        self
    }

    /// A `[[modbus_tcp.unit_map]]`: Modbus TCP unit ids `units` go to
    /// `bus`, as its units `bus_units` (ranges like `"101-132"`).
    pub fn unit_map(mut self, units: &str, bus: &str, bus_units: &str) -> Self {
        self.modbus_tcp_tables.push(format!(
            "[[modbus_tcp.unit_map]]\nunits = \"{units}\"\nbus = \"{bus}\"\nbus_units = \"{bus_units}\"\n"
        ));
        self
    }

    /// Key lines added to the section `[name]` (`safety`, `log`, `monitor`,
    /// `scope`...); a section named twice gets both sets of keys.
    pub fn section(mut self, name: &str, keys: &str) -> Self {
        match self.sections.iter_mut().find(|(n, _)| n == name) {
            Some((_, lines)) => push_lines(lines, keys),
            None => {
                let mut lines = Vec::new();
                push_lines(&mut lines, keys);
                self.sections.push((name.to_string(), lines));
            }
        }
        self
    }

    /// A `[[bus]]` named `name`, on the built-in simulator until
    /// [`BusBuilder::port`] says otherwise, shaped by `f`.
    pub fn bus(mut self, name: &str, f: impl FnOnce(BusBuilder) -> BusBuilder) -> Self {
        self.buses.push(f(BusBuilder::new(name)));
        self
    }

    /// Changes the bus named `name` (added by [`bus`](Self::bus) or a
    /// preset such as [`four_drives`](Self::four_drives)); panics if there
    /// is none, since a change that silently did nothing would test
    /// something else.
    pub fn with_bus(mut self, name: &str, f: impl FnOnce(BusBuilder) -> BusBuilder) -> Self {
        let i = self
            .buses
            .iter()
            .position(|b| b.name == name)
            .unwrap_or_else(|| panic!("no bus {name:?} in the configuration"));
        let bus = self.buses.remove(i);
        self.buses.insert(i, f(bus));
        self
    }

    /// Whole tables written out, appended after everything else: for
    /// what the builder has no words for, and for a caller's own text.
    pub fn tables(mut self, toml: &str) -> Self {
        self.tables.push_str(toml);
        self.tables.push('\n');
        self
    }

    /// The TOML the daemon reads.
    pub fn toml(&self) -> String {
        let mut out = String::from("[http]\n");
        push_block(&mut out, &self.http);
        // Tables of [[http.token]] come after every plain [http] key.
        for token in &self.tokens {
            out.push_str(token);
        }
        out.push_str("[modbus_tcp]\n");
        match &self.modbus_tcp {
            Some(lines) => push_block(&mut out, lines),
            None => out.push_str("enabled = false\n"),
        }
        for table in &self.modbus_tcp_tables {
            out.push_str(table);
        }
        for (name, lines) in &self.sections {
            out.push_str(&format!("[{name}]\n"));
            push_block(&mut out, lines);
        }
        for bus in &self.buses {
            bus.render(&mut out);
        }
        out.push_str(&self.tables);
        out
    }
}

/// One `[[bus]]` of a [`ConfigBuilder`]: the built-in simulator with the
/// tests' [`WIRE_TIMING`] and one retry, until told otherwise.
#[derive(Debug, Clone)]
pub struct BusBuilder {
    name: String,
    port: String,
    keys: Vec<String>,
    sim: Vec<String>,
    sim_faults: Vec<String>,
    drives: Vec<Drive>,
}

/// One `[[bus.drive]]`.
#[derive(Debug, Clone)]
struct Drive {
    unit: u8,
    name: String,
    gear_ratio: Option<f64>,
    keys: Vec<String>,
}

impl BusBuilder {
    fn new(name: &str) -> Self {
        let mut keys = Vec::new();
        push_lines(&mut keys, WIRE_TIMING);
        keys.push("retries = 1".into());
        BusBuilder {
            name: name.to_string(),
            port: "sim".into(),
            keys,
            sim: vec!["turnaround_ms = 0.5".into()],
            sim_faults: Vec::new(),
            drives: Vec::new(),
        }
    }

    /// The serial port (a path, `tcp://host:port`, or `"sim"`); a bus that
    /// is not on the built-in simulator has no `[bus.sim]`.
    pub fn port(mut self, port: &str) -> Self {
        self.port = port.to_string();
        self
    }

    /// Key lines of the `[[bus]]` (e.g. `"poll_interval_ms = 1000"`); a key
    /// already set (the timing, `retries`) is replaced, not repeated.
    pub fn keys(mut self, keys: &str) -> Self {
        for line in keys.lines().map(str::trim).filter(|l| !l.is_empty()) {
            let key = key_of(line);
            self.keys.retain(|l| key_of(l) != key);
            self.keys.push(line.to_string());
        }
        self
    }

    /// The response timeout and the guard time after a silent drive, ms.
    pub fn timing(self, response_timeout_ms: u64, guard_ms: u64) -> Self {
        self.keys(&format!(
            "response_timeout_ms = {response_timeout_ms}\nguard_ms = {guard_ms}"
        ))
    }

    /// Key lines of `[bus.sim]` (e.g. `"seed = 11"`); a key already set is
    /// replaced.
    pub fn sim(mut self, keys: &str) -> Self {
        for line in keys.lines().map(str::trim).filter(|l| !l.is_empty()) {
            let key = key_of(line);
            self.sim.retain(|l| key_of(l) != key);
            self.sim.push(line.to_string());
        }
        self
    }

    /// Key lines of `[bus.sim.faults]`: the wire faults the simulator
    /// injects.
    pub fn sim_faults(mut self, keys: &str) -> Self {
        push_lines(&mut self.sim_faults, keys);
        self
    }

    /// No `guard_ms`: the guard time after a silent drive is the one the
    /// daemon works out from the line.
    pub fn auto_guard(mut self) -> Self {
        self.keys.retain(|l| key_of(l) != "guard_ms");
        self
    }

    /// A drive at `unit` named `name`, with the default gear ratio.
    pub fn drive(mut self, unit: u8, name: &str) -> Self {
        self.drives.push(Drive {
            unit,
            name: name.to_string(),
            gear_ratio: None,
            keys: Vec::new(),
        });
        self
    }

    /// A drive at `unit` named `name` behind a gear of `ratio`.
    pub fn geared_drive(mut self, unit: u8, name: &str, ratio: f64) -> Self {
        self.drives.push(Drive {
            unit,
            name: name.to_string(),
            gear_ratio: Some(ratio),
            keys: Vec::new(),
        });
        self
    }

    /// Key lines added to the drive named `name` (e.g.
    /// `"poll_interval_ms = 60000"`); panics if the bus has no such drive.
    pub fn drive_keys(mut self, name: &str, keys: &str) -> Self {
        let drive = self
            .drives
            .iter_mut()
            .find(|d| d.name == name)
            .unwrap_or_else(|| panic!("no drive {name:?} on bus {:?}", self.name));
        push_lines(&mut drive.keys, keys);
        self
    }

    /// Drives at `units`, each named `d<unit>`, gear 3.75.
    pub fn drives(self, units: impl IntoIterator<Item = u8>) -> Self {
        units.into_iter().fold(self, |b, unit| {
            b.geared_drive(unit, &format!("d{unit}"), 3.75)
        })
    }

    fn render(&self, out: &mut String) {
        out.push_str(&format!(
            "[[bus]]\nname = \"{}\"\nport = \"{}\"\n",
            self.name, self.port
        ));
        push_block(out, &self.keys);
        if self.port == "sim" {
            out.push_str("[bus.sim]\n");
            push_block(out, &self.sim);
            if !self.sim_faults.is_empty() {
                out.push_str("[bus.sim.faults]\n");
                push_block(out, &self.sim_faults);
            }
        }
        for drive in &self.drives {
            out.push_str(&format!(
                "[[bus.drive]]\nunit = {}\nname = \"{}\"\n",
                drive.unit, drive.name
            ));
            if let Some(ratio) = drive.gear_ratio {
                out.push_str(&format!("gear_ratio = {ratio:?}\n"));
            }
            push_block(out, &drive.keys);
        }
    }
}

/// SHA-256 of a bearer token, in hex, as `[[http.token]] sha256` holds it.
pub fn sha256_hex(token: &str) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(token.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The key of a `key = value` line.
fn key_of(line: &str) -> &str {
    line.split('=').next().unwrap_or("").trim()
}

fn push_lines(lines: &mut Vec<String>, keys: &str) {
    lines.extend(
        keys.lines()
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .map(String::from),
    );
}

fn push_block(out: &mut String, lines: &[String]) {
    for line in lines {
        out.push_str(line);
        out.push('\n');
    }
}
