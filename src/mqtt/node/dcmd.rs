//! Commands from hosts (DCMD): a DCMD's metrics in order, through the
//! control core with a caller in the MQTT session, in a task of their own;
//! each result comes back to the node and is published as the metric's
//! confirmed value or `command/last_result` with the words. A DCMD that
//! is not live (retained, or queued for an earlier session) is refused by
//! the core whole, before any of its metrics, and answered the same way.

use prost::Message;

use super::command_result::CommandResult;
use super::{Connection, Node, now_ms};
use crate::control::Failure;
use crate::mqtt::metric::{self, LAST_RESULT, Value, Writable};
use crate::mqtt::metric_commands::{self, Command};
use crate::mqtt::sparkplug_b::{DataType, Payload};

impl Node {
    /// A DCMD for `device` (`retained`: its retain flag on delivery): its
    /// metrics in order, through the core, in a task of their own.
    pub(super) fn on_dcmd(
        &mut self,
        c: &Connection,
        device: String,
        payload: &[u8],
        retained: bool,
    ) {
        let Ok(target) = self.control.target(&device) else {
            self.metrics.mqtt().command("malformed");
            tracing::warn!(
                device,
                "MQTT: a DCMD for a device that is not a configured drive: ignored"
            );
            return;
        };
        let Ok(p) = Payload::decode(payload) else {
            self.metrics.mqtt().command("malformed");
            self.last_result(
                Some(c),
                &device,
                "the DCMD is no Sparkplug B payload".to_string(),
            );
            return;
        };
        let caller = self.caller();
        let delivery = self.connected.delivery(retained, p.timestamp);
        if let Err(refusal) =
            self.control
                .check_live(&caller, &device, &metrics_in_words(&p), delivery)
        {
            self.metrics.mqtt().command("refused");
            let names = metric_names(&p);
            let words = format!("{names}: {}", Failure::Refused(refusal));
            self.last_result(Some(c), &device, words);
            return;
        }
        let mut run: Vec<Command> = Vec::new();
        for m in &p.metrics {
            match metric_commands::parse(m) {
                Ok(Some(cmd)) => run.push(cmd),
                Ok(None) => {}
                Err(malformed) => {
                    self.metrics.mqtt().command("malformed");
                    if let Some(what) = malformed.1 {
                        // A write the drive cannot take is audited like
                        // every refused write.
                        self.control.refused(
                            &caller,
                            target,
                            what,
                            format!("refused: {}", malformed.0),
                        );
                    }
                    self.last_result(Some(c), &device, malformed.0);
                }
            }
        }
        if run.is_empty() {
            return;
        }
        self.session.active();
        let control = self.control.clone();
        let results = self.results_tx.clone();
        // Finished commands' handles go; the others stay to be aborted
        // with their session.
        while self.commands.try_join_next().is_some() {}
        self.commands.spawn(async move {
            for cmd in run {
                let outcome = metric_commands::run(&control, &caller, target, &cmd)
                    .await
                    .map(|()| metric_commands::confirmed_value(&cmd))
                    .map_err(|f| f.to_string());
                let failed = outcome.is_err();
                let _ = results.send(CommandResult {
                    device: device.clone(),
                    metric: cmd.metric,
                    outcome,
                });
                // The rest of a DCMD whose command failed is not sent: a
                // setpoint after a refused mode would go to the wrong mode.
                if failed {
                    break;
                }
            }
        });
    }

    /// A command's result: the metric's confirmed value (and an empty
    /// `command/last_result`), or the words of its refusal or failure.
    pub(super) fn on_result(&mut self, c: Option<&Connection>, result: CommandResult) {
        let now = now_ms();
        let device = self.devices.entry(result.device.clone()).or_default();
        let mut metrics = Vec::new();
        match result.outcome {
            Ok(value) => {
                self.metrics.mqtt().command("confirmed");
                match (&value, result.metric) {
                    (Value::Double(v), Writable::SpeedRpm) => device.setpoints.speed_rpm = Some(*v),
                    (Value::Double(v), Writable::PositionDeg) => {
                        device.setpoints.position_deg = Some(*v);
                    }
                    (Value::Double(v), Writable::TorqueA) => device.setpoints.torque_a = Some(*v),
                    _ => {}
                }
                device.last_result.clear();
                metrics.push(metric::metric(
                    result.metric.name(),
                    result.metric.datatype(),
                    value,
                    now,
                ));
                metrics.push(metric::metric(
                    LAST_RESULT,
                    DataType::String,
                    Value::Text(String::new()),
                    now,
                ));
            }
            Err(words) => {
                let refused = words.starts_with("refused");
                self.metrics
                    .mqtt()
                    .command(if refused { "refused" } else { "failed" });
                let words = format!("{}: {words}", result.metric.name());
                device.last_result = words.clone();
                metrics.push(metric::metric(
                    LAST_RESULT,
                    DataType::String,
                    Value::Text(words),
                    now,
                ));
            }
        }
        self.device_data(c, &result.device, metrics);
    }

    /// `command/last_result` of `device` set to `words`, and published.
    fn last_result(&mut self, c: Option<&Connection>, device: &str, words: String) {
        let now = now_ms();
        self.devices
            .entry(device.to_string())
            .or_default()
            .last_result = words.clone();
        self.device_data(
            c,
            device,
            vec![metric::metric(
                LAST_RESULT,
                DataType::String,
                Value::Text(words),
                now,
            )],
        );
    }
}

/// The metrics of a DCMD and their values, for the audit log:
/// `command/activate = true, setpoint/speed_rpm = 123`.
fn metrics_in_words(p: &Payload) -> String {
    let words: Vec<String> = p
        .metrics
        .iter()
        .map(|m| {
            let value = match metric::value_of(m) {
                Value::Bool(b) => b.to_string(),
                Value::Double(v) => v.to_string(),
                Value::Int(v) => v.to_string(),
                Value::UInt(v) => v.to_string(),
                Value::Text(t) => t,
                Value::Null => "null".to_string(),
            };
            format!("DCMD {} = {value}", m.name.as_deref().unwrap_or("?"))
        })
        .collect();
    if words.is_empty() {
        "a DCMD without metrics".to_string()
    } else {
        words.join(", ")
    }
}

/// The names of a DCMD's metrics, as `command/last_result` begins.
fn metric_names(p: &Payload) -> String {
    let names: Vec<&str> = p.metrics.iter().filter_map(|m| m.name.as_deref()).collect();
    if names.is_empty() {
        "DCMD".to_string()
    } else {
        names.join(", ")
    }
}
