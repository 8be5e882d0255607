//! The JSON format's topics under `topic_prefix` (pure):
//! `<prefix>/state`, and per drive `<prefix>/<drive>/status`, `/event`,
//! `/command` (taken) and `/reply`.

/// The topics of one gateway.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct JsonTopics {
    prefix: String,
}

impl JsonTopics {
    /// The topics under `prefix` (already checked: no wildcard, no empty
    /// level).
    pub fn new(prefix: &str) -> Self {
        JsonTopics {
            prefix: prefix.to_string(),
        }
    }

    /// The default prefix: `drivegate/<node_id>`.
    pub fn default_prefix(node_id: &str) -> String {
        format!("drivegate/{node_id}")
    }

    /// The prefix.
    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    /// `online`/`offline`, retained; `offline` is the MQTT will.
    pub fn state(&self) -> String {
        format!("{}/state", self.prefix)
    }

    /// A drive's status, retained.
    pub fn status(&self, drive: &str) -> String {
        format!("{}/{drive}/status", self.prefix)
    }

    /// A drive's events: online, offline, lease news.
    pub fn event(&self, drive: &str) -> String {
        format!("{}/{drive}/event", self.prefix)
    }

    /// The gateway's own events: bus-wide alarms.
    pub fn gateway_event(&self) -> String {
        format!("{}/event", self.prefix)
    }

    /// Replies to commands without a response topic.
    pub fn reply(&self, drive: &str) -> String {
        format!("{}/{drive}/reply", self.prefix)
    }

    /// The subscription that takes every drive's commands.
    pub fn command_filter(&self) -> String {
        format!("{}/+/command", self.prefix)
    }

    /// The drive a command topic names, if `topic` is one of this
    /// gateway's command topics.
    pub fn command_drive<'a>(&self, topic: &'a str) -> Option<&'a str> {
        let rest = topic
            .strip_prefix(self.prefix.as_str())?
            .strip_prefix('/')?;
        let drive = rest.strip_suffix("/command")?;
        (!drive.is_empty() && !drive.contains('/')).then_some(drive)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topics_under_the_prefix() {
        let t = JsonTopics::new(&JsonTopics::default_prefix("gw1"));
        assert_eq!(t.state(), "drivegate/gw1/state");
        assert_eq!(t.status("conveyor"), "drivegate/gw1/conveyor/status");
        assert_eq!(t.event("conveyor"), "drivegate/gw1/conveyor/event");
        assert_eq!(t.reply("conveyor"), "drivegate/gw1/conveyor/reply");
        assert_eq!(t.command_filter(), "drivegate/gw1/+/command");
        assert_eq!(t.gateway_event(), "drivegate/gw1/event");
    }

    #[test]
    fn command_topics_name_their_drive() {
        let t = JsonTopics::new("plant/line3");
        assert_eq!(t.command_drive("plant/line3/lift/command"), Some("lift"));
        for other in [
            "plant/line3/lift/status",
            "plant/line3//command",
            "plant/line3/a/b/command",
            "plant/line30/lift/command",
            "plant/line3/command",
            "other/lift/command",
        ] {
            assert_eq!(t.command_drive(other), None, "{other}");
        }
    }
}
