//! Who a command from MQTT comes from, as far as drivegate can know it.
//!
//! MQTT carries no publisher identity: a DCMD (or a JSON command) says
//! nothing the broker vouches for about who sent it. What drivegate knows
//! is how it logged in itself (the broker's user, or its client
//! certificate), so that the broker's ACL for that user's topics is what
//! decides who may command; and, with Sparkplug, which primary host
//! *claims* to be in charge (its `STATE`, which any client allowed to
//! publish there could send). The audit log, the leases and the bus
//! monitor say exactly that, and nothing more:
//! `broker user gw1; primary host "scada" claimed`. This module says the
//! login; the core ([`crate::control::identity`], `Credential::Broker`)
//! adds the host claimed and gives the role (`[mqtt] commands`).

use crate::config::MqttConfig;
use crate::config::mqtt::Login;

/// How the broker knows drivegate's connection, the first part of the
/// `who` of the MQTT face's commands (audit log, lease owner, bus monitor).
pub fn login(config: &MqttConfig) -> String {
    match config.login() {
        Login::User(user) => format!("broker user {user}"),
        Login::Certificate => match certificate_name(config) {
            Some(cn) => format!("broker certificate \"{cn}\""),
            None => "broker certificate".to_string(),
        },
        Login::Anonymous => config.anonymous_name(),
    }
}

/// The subject CN of drivegate's own client certificate, if it can be
/// read (a file that cannot fails the connection later, in words).
fn certificate_name(config: &MqttConfig) -> Option<String> {
    let path = config.client_cert.as_ref()?.get_ref();
    let chain = crate::tls::load_certificates(path, "MQTT client certificate").ok()?;
    crate::tls::peer_identity(chain.first()?, "")
        .ok()?
        .common_name
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    use crate::config::{Config, Role};
    use crate::control::Face;
    use crate::control::identity::{Credential, identify};

    fn config(keys: &str) -> Config {
        let toml = format!("[mqtt]\nbroker = \"mqtt://10.0.0.5:1883\"\n{keys}\n");
        Config::parse(&toml, "test").unwrap()
    }

    /// The who and role of commands, as the face asks the core for them.
    fn who(config: &Config, primary_host: Option<&str>) -> (String, Role) {
        let login = login(config.mqtt.as_ref().unwrap());
        let credential = Credential::Broker {
            login: &login,
            primary_host,
        };
        let identity = identify(config, Face::Mqtt, credential).unwrap();
        (identity.who.to_string(), identity.role)
    }

    #[test]
    fn says_only_what_is_known() {
        let c = config("commands = \"operator\"\nusername = \"gw1\"\npassword_file = \"/x\"");
        assert_eq!(
            who(&c, Some("scada")),
            (
                "broker user gw1; primary host \"scada\" claimed".to_string(),
                Role::Operator
            )
        );
        assert_eq!(who(&c, None).0, "broker user gw1");
        let c = config("commands = \"admin\"\nunauthenticated_commands = true");
        assert_eq!(
            who(&c, None),
            (
                "unauthenticated broker 10.0.0.5:1883".to_string(),
                Role::Admin
            )
        );
        // A user without a password is no login; no commands, a viewer's
        // role (the core refuses every write in its own words).
        let c = config("username = \"gw1\"");
        assert_eq!(
            who(&c, None),
            (
                "unauthenticated broker 10.0.0.5:1883".to_string(),
                Role::Viewer
            )
        );
    }
}
