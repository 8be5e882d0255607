//! The control core's own counters, read at scrape time: the ends of the
//! leases of Modbus TCP clients' and of the MQTT session's
//! communication-loss function, per bus,
//! the safety journal, and the drift of drives from their declared
//! settings.
//! Every bus's series exist from start-up, at 0, so an alert on
//! `increase(...) > 0` needs no `absent()`.

use prometheus::core::{Collector, Desc};
use prometheus::proto::MetricFamily;

use super::family::{Kind, Spec};
use crate::control::journal::Health;
use crate::control::{Control, Face};

static COMM_LOSS: Spec = Spec {
    name: "drivegate_modbus_tcp_comm_loss_stops_total",
    help: "Leases of Modbus TCP clients' communication-loss function that ended, each followed \
           by the network's comm_loss_action (none: nothing sent), by reason: timeout (no \
           request within comm_loss_ms) or closed (the connection closed).",
    kind: Kind::Counter,
    labels: &["bus", "reason"],
};

static OPCUA_COMM_LOSS: Spec = Spec {
    name: "drivegate_opcua_comm_loss_stops_total",
    help: "Leases of OPC UA sessions' setpoints and modes that ended with [opcua] \
           comm_loss_action (none: nothing sent), by reason: timeout (no request within the \
           session's timeout) or closed (the session was closed, or timed out on the server).",
    kind: Kind::Counter,
    labels: &["bus", "reason"],
};

static MQTT_COMM_LOSS: Spec = Spec {
    name: "drivegate_mqtt_comm_loss_stops_total",
    help: "Leases of commands from MQTT that ended with the MQTT session's comm_loss_action \
           (none: nothing sent), by reason: timeout (the broker lost for longer than \
           comm_loss_ms) or closed (the session ended: the primary host's STATE went offline).",
    kind: Kind::Counter,
    labels: &["bus", "reason"],
};

static REPLAYED: Spec = Spec {
    name: "drivegate_restart_decisions_total",
    help: "Decisions of the start-up replay of the safety journal, by decision: stops owed \
           (holder gone, ran out, unfinished, brake again, unknown state, journal lost), HTTP \
           leases kept, stops not sent because a confirmed brake holds, drives no longer \
           configured, moving drives left moving with on_unknown_state = none.",
    kind: Kind::Counter,
    labels: &["decision"],
};

static JOURNAL_OK: Spec = Spec {
    name: "drivegate_safety_journal_ok",
    help: "1 when the safety journal is written and synced; 0 when there is none or it cannot \
           be written (leases then work in memory only and are not kept across a restart).",
    kind: Kind::Gauge,
    labels: &[],
};

static JOURNAL_EVENTS: Spec = Spec {
    name: "drivegate_safety_journal_events_total",
    help: "The safety journal's life: records appended, write errors, compactions, journals \
           found unreadable at start-up (set aside, renamed, when they could be), and journals \
           found lost at start-up (empty, only a header, or missing after an earlier run).",
    kind: Kind::Counter,
    labels: &["event"],
};

static JOURNAL_BYTES: Spec = Spec {
    name: "drivegate_safety_journal_bytes",
    help: "Size of the safety journal file.",
    kind: Kind::Gauge,
    labels: &[],
};

static JOURNAL_SKIPPED: Spec = Spec {
    name: "drivegate_safety_journal_skipped_bytes",
    help: "Bytes of the safety journal skipped unread at start-up: it is read from its end back \
           to its last clean stop, its start, or 64 KiB and 4 KiB per drive (a longer one was \
           not written by this daemon, which compacts it); 0 when it was read whole.",
    kind: Kind::Gauge,
    labels: &[],
};

static RELOADS: Spec = Spec {
    name: "drivegate_config_reload_total",
    help: "Reloads of the configuration file (SIGHUP or POST /api/v1/config/reload), by \
           result: applied, partial (applied, but a bus's port did not open or a listener \
           could not move: /readyz says what) or invalid (the file did not pass the check; the \
           running configuration stayed).",
    kind: Kind::Counter,
    labels: &["result"],
};

static RELOAD_OK: Spec = Spec {
    name: "drivegate_config_last_reload_ok",
    help: "0 while the last reload of the configuration file was refused or applied only in \
           part (the file on disk is not the one running: /readyz says why, with \
           file:line:column, or what was not done); 1 otherwise.",
    kind: Kind::Gauge,
    labels: &[],
};

static DRIFT: Spec = Spec {
    name: "drivegate_drive_settings_drift",
    help: "1 while a drive with declared settings ([bus.drive.settings]) is known not to hold \
           them, 0 once it was compared and holds them; no series before its first comparison \
           (it compares when the drive comes online) nor for drives without a declaration.",
    kind: Kind::Gauge,
    labels: &["bus", "unit", "name"],
};

static ALARMS_ACTIVE: Spec = Spec {
    name: "drivegate_alarms_active",
    help: "Active alarms by kind: fault, stall, offline, never-answered, bus-down, stop-failed \
           (conditions that last), comm-loss, refused-write and unknown-state (events: never \
           active, see drivegate_alarms_unacknowledged).",
    kind: Kind::Gauge,
    labels: &["kind"],
};

static ALARMS_UNACKED: Spec = Spec {
    name: "drivegate_alarms_unacknowledged",
    help: "Alarms no operator has acknowledged yet, active or not (GET /api/v1/alarms).",
    kind: Kind::Gauge,
    labels: &[],
};

static LOADED_AT: Spec = Spec {
    name: "drivegate_config_last_reload_success_timestamp_seconds",
    help: "When the running configuration was loaded: at start-up or by the last reload \
           applied (Unix time).",
    kind: Kind::Gauge,
    labels: &[],
};

static ALARM_FILE_BYTES: Spec = Spec {
    name: "drivegate_alarm_file_bytes",
    help: "Size of the alarm file (alarms.journal in [safety] state_dir); 0 without one.",
    kind: Kind::Gauge,
    labels: &[],
};

static ALARM_FILE_OK: Spec = Spec {
    name: "drivegate_alarm_file_ok",
    help: "1 when the alarm file is written and synced (or there is no state directory); 0            when it cannot be written (alarms are then kept in memory until it can).",
    kind: Kind::Gauge,
    labels: &[],
};

static ALARM_FILE_SKIPPED: Spec = Spec {
    name: "drivegate_alarm_file_skipped_bytes",
    help: "Bytes of the alarm file skipped unread at start-up: it is read from its end until it \
           gave [safety] alarms_kept alarms; 0 when it was read whole.",
    kind: Kind::Gauge,
    labels: &[],
};

/// Exports the control core's counters.
pub(crate) struct ControlCollector {
    control: Control,
    descs: Vec<Desc>,
}

impl ControlCollector {
    pub(crate) fn new(control: Control) -> Self {
        Self {
            control,
            descs: vec![
                COMM_LOSS.desc(),
                MQTT_COMM_LOSS.desc(),
                OPCUA_COMM_LOSS.desc(),
                REPLAYED.desc(),
                JOURNAL_OK.desc(),
                JOURNAL_EVENTS.desc(),
                JOURNAL_BYTES.desc(),
                JOURNAL_SKIPPED.desc(),
                RELOADS.desc(),
                RELOAD_OK.desc(),
                LOADED_AT.desc(),
                DRIFT.desc(),
                ALARMS_ACTIVE.desc(),
                ALARMS_UNACKED.desc(),
                ALARM_FILE_BYTES.desc(),
                ALARM_FILE_OK.desc(),
                ALARM_FILE_SKIPPED.desc(),
            ],
        }
    }
}

impl Collector for ControlCollector {
    fn desc(&self) -> Vec<&Desc> {
        self.descs.iter().collect()
    }

    fn collect(&self) -> Vec<MetricFamily> {
        let mut comm_loss = COMM_LOSS.family();
        let mut mqtt_comm_loss = MQTT_COMM_LOSS.family();
        let mut opcua_comm_loss = OPCUA_COMM_LOSS.family();
        for (i, bus) in self.control.plant().now().indexed_buses() {
            let name = bus.handle.name();
            for (family, face) in [
                (&mut comm_loss, Face::ModbusTcp),
                (&mut mqtt_comm_loss, Face::Mqtt),
                (&mut opcua_comm_loss, Face::OpcUa),
            ] {
                let (timeout, closed) = self.control.comm_loss_ends(i, face);
                family.set(&[name, "timeout"], timeout as f64);
                family.set(&[name, "closed"], closed as f64);
            }
        }
        let mut replayed = REPLAYED.family();
        let counts = self.control.replayed();
        for kind in crate::control::restart::DecisionKind::ALL {
            replayed.set(
                &[kind.name()],
                counts.get(&kind).copied().unwrap_or(0) as f64,
            );
        }
        let (health, c) = self.control.journal();
        let mut ok = JOURNAL_OK.family();
        ok.set(&[], f64::from(u8::from(health == Health::Ok)));
        let mut events = JOURNAL_EVENTS.family();
        events.set(&["record"], c.records as f64);
        events.set(&["write-error"], c.write_errors as f64);
        events.set(&["compaction"], c.compactions as f64);
        events.set(&["unreadable"], c.unreadable as f64);
        events.set(&["lost"], c.lost as f64);
        let mut bytes = JOURNAL_BYTES.family();
        bytes.set(&[], c.bytes as f64);
        let mut journal_skipped = JOURNAL_SKIPPED.family();
        journal_skipped.set(&[], c.skipped_bytes as f64);
        let status = self.control.reload_status();
        let mut reloads = RELOADS.family();
        reloads.set(&["applied"], status.applied as f64);
        reloads.set(&["partial"], status.partial as f64);
        reloads.set(&["invalid"], status.invalid as f64);
        let mut reload_ok = RELOAD_OK.family();
        reload_ok.set(&[], f64::from(u8::from(status.last_ok)));
        let mut loaded_at = LOADED_AT.family();
        if let Some(at) = status
            .last_good_at
            .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        {
            loaded_at.set(&[], at.as_secs_f64());
        }
        let mut drift = DRIFT.family();
        let plant = self.control.plant().now();
        for d in plant.drives().filter(|d| d.declared.is_some()) {
            if let Some(view) = self.control.drift().view(&d.name) {
                let unit = d.unit.to_string();
                let Some(bus) = plant.handle_of(d).map(|h| h.name()) else {
                    continue;
                };
                drift.set_bool(&[bus, unit.as_str(), d.name.as_str()], view.drifted());
            }
        }
        let summary = self.control.alarms().summary();
        let mut active = ALARMS_ACTIVE.family();
        for (kind, n) in &summary.active {
            active.set(&[kind.name()], *n as f64);
        }
        let mut unacked = ALARMS_UNACKED.family();
        unacked.set(&[], summary.unacknowledged as f64);
        let file = self.control.alarms().file_state();
        let mut file_bytes = ALARM_FILE_BYTES.family();
        file_bytes.set(&[], file.bytes as f64);
        let mut file_ok = ALARM_FILE_OK.family();
        file_ok.set(&[], f64::from(u8::from(file.failing.is_none())));
        let mut file_skipped = ALARM_FILE_SKIPPED.family();
        file_skipped.set(&[], file.skipped_bytes as f64);
        vec![
            reloads.finish(),
            reload_ok.finish(),
            loaded_at.finish(),
            comm_loss.finish(),
            mqtt_comm_loss.finish(),
            opcua_comm_loss.finish(),
            drift.finish(),
            replayed.finish(),
            ok.finish(),
            events.finish(),
            bytes.finish(),
            journal_skipped.finish(),
            active.finish(),
            unacked.finish(),
            file_bytes.finish(),
            file_ok.finish(),
            file_skipped.finish(),
        ]
    }
}
