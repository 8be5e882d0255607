//! Sparkplug B topic names (spec 3.0, section 4.1): building the edge
//! node's and its devices' topics and telling what an incoming topic is.
//! Pure: no I/O.

/// The Sparkplug B namespace, the first level of every topic.
pub const NAMESPACE: &str = "spBv1.0";

/// The node's identity in topics.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NodeTopics {
    group: String,
    node: String,
}

/// A Sparkplug message type the node sends or takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// Node birth.
    NBirth,
    /// Node death (the will).
    NDeath,
    /// Node data (a bus's state).
    NData,
    /// Device birth.
    DBirth,
    /// Device death.
    DDeath,
    /// Device data.
    DData,
    /// Node command.
    NCmd,
    /// Device command.
    DCmd,
}

impl Kind {
    /// The topic level.
    pub fn level(self) -> &'static str {
        match self {
            Kind::NBirth => "NBIRTH",
            Kind::NDeath => "NDEATH",
            Kind::NData => "NDATA",
            Kind::DBirth => "DBIRTH",
            Kind::DDeath => "DDEATH",
            Kind::DData => "DDATA",
            Kind::NCmd => "NCMD",
            Kind::DCmd => "DCMD",
        }
    }

    /// The metrics' label for it (`nbirth`, ...).
    pub fn label(self) -> &'static str {
        match self {
            Kind::NBirth => "nbirth",
            Kind::NDeath => "ndeath",
            Kind::NData => "ndata",
            Kind::DBirth => "dbirth",
            Kind::DDeath => "ddeath",
            Kind::DData => "ddata",
            Kind::NCmd => "ncmd",
            Kind::DCmd => "dcmd",
        }
    }
}

/// What an incoming message is.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Incoming<'a> {
    /// A command to the node (`Node Control/Rebirth`).
    NodeCommand,
    /// A command to device (drive) `device`.
    DeviceCommand {
        /// The device id: the drive's name.
        device: &'a str,
    },
    /// A primary host's `STATE` (spec 3.0: `spBv1.0/STATE/<host_id>`).
    State {
        /// The host's id.
        host: &'a str,
    },
    /// Nothing the node serves.
    Other,
}

impl NodeTopics {
    /// Topics of node `node` in group `group` (both checked by the
    /// configuration: no `/`, `+` or `#`).
    pub fn new(group: &str, node: &str) -> Self {
        NodeTopics {
            group: group.to_string(),
            node: node.to_string(),
        }
    }

    /// The node id.
    pub fn node(&self) -> &str {
        &self.node
    }

    /// The topic of a node message (`NBIRTH`, `NDEATH`, `NCMD`).
    pub fn node_topic(&self, kind: Kind) -> String {
        format!("{NAMESPACE}/{}/{}/{}", self.group, kind.level(), self.node)
    }

    /// The topic of a device message of `device`.
    pub fn device_topic(&self, kind: Kind, device: &str) -> String {
        format!(
            "{NAMESPACE}/{}/{}/{}/{device}",
            self.group,
            kind.level(),
            self.node
        )
    }

    /// The filters the node subscribes to: its NCMD, its devices' DCMD.
    pub fn command_filters(&self) -> [String; 2] {
        [
            self.node_topic(Kind::NCmd),
            format!("{NAMESPACE}/{}/DCMD/{}/+", self.group, self.node),
        ]
    }

    /// What `topic` is, for this node.
    pub fn classify<'a>(&self, topic: &'a str) -> Incoming<'a> {
        let mut levels = topic.split('/');
        if levels.next() != Some(NAMESPACE) {
            return Incoming::Other;
        }
        let rest: Vec<&'a str> = levels.collect();
        match rest.as_slice() {
            ["STATE", host] => Incoming::State { host },
            [group, "NCMD", node] if *group == self.group && *node == self.node => {
                Incoming::NodeCommand
            }
            [group, "DCMD", node, device] if *group == self.group && *node == self.node => {
                Incoming::DeviceCommand { device }
            }
            _ => Incoming::Other,
        }
    }
}

/// The `STATE` topic of primary host `host`.
pub fn state_topic(host: &str) -> String {
    format!("{NAMESPACE}/STATE/{host}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn topics_follow_the_namespace() {
        let t = NodeTopics::new("plant", "gw1");
        assert_eq!(t.node_topic(Kind::NBirth), "spBv1.0/plant/NBIRTH/gw1");
        assert_eq!(
            t.device_topic(Kind::DData, "conveyor"),
            "spBv1.0/plant/DDATA/gw1/conveyor"
        );
        assert_eq!(
            t.command_filters(),
            [
                "spBv1.0/plant/NCMD/gw1".to_string(),
                "spBv1.0/plant/DCMD/gw1/+".to_string()
            ]
        );
        assert_eq!(state_topic("scada"), "spBv1.0/STATE/scada");
    }

    #[test]
    fn incoming_topics_are_told_apart() {
        let t = NodeTopics::new("plant", "gw1");
        assert_eq!(t.classify("spBv1.0/plant/NCMD/gw1"), Incoming::NodeCommand);
        assert_eq!(
            t.classify("spBv1.0/plant/DCMD/gw1/lift"),
            Incoming::DeviceCommand { device: "lift" }
        );
        assert_eq!(
            t.classify("spBv1.0/STATE/scada"),
            Incoming::State { host: "scada" }
        );
        // Another node's, another group's, or not Sparkplug at all.
        assert_eq!(t.classify("spBv1.0/plant/NCMD/gw2"), Incoming::Other);
        assert_eq!(t.classify("spBv1.0/other/DCMD/gw1/lift"), Incoming::Other);
        assert_eq!(t.classify("spBv1.0/plant/DCMD/gw1/a/b"), Incoming::Other);
        assert_eq!(t.classify("plant/DCMD/gw1/lift"), Incoming::Other);
    }
}
