//! Host names and browser origins as `[http] allowed_hosts` and
//! `allowed_origins` write them, and as browsers send them in `Host` and
//! `Origin`: parsed and normalised here, below the HTTP face whose guard
//! (`api::guard`) compares them, so the configuration checks its entries
//! with the same code that will match them.

use std::net::IpAddr;

/// A web origin: scheme, host and port (the default port filled in).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct WebOrigin {
    scheme: String,
    host: String,
    port: u16,
}

impl WebOrigin {
    /// The origin of `scheme://host:port`.
    pub fn new(scheme: &str, host: String, port: u16) -> WebOrigin {
        WebOrigin {
            scheme: scheme.to_ascii_lowercase(),
            host,
            port,
        }
    }

    /// Parses `scheme://host[:port]` as browsers send it in `Origin`;
    /// `None` for anything else (`null`, paths, other schemes).
    pub fn parse(text: &str) -> Option<WebOrigin> {
        let text = text.trim();
        let (scheme, rest) = text.split_once("://")?;
        let scheme = scheme.to_ascii_lowercase();
        let default_port = match scheme.as_str() {
            "http" => 80,
            "https" => 443,
            _ => return None,
        };
        let rest = rest.strip_suffix('/').unwrap_or(rest);
        if rest.contains(['/', '?', '#', '@']) {
            return None;
        }
        let (host, port) = split_host(rest)?;
        Some(WebOrigin {
            scheme,
            host,
            port: port.unwrap_or(default_port),
        })
    }
}

impl std::fmt::Display for WebOrigin {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let default = matches!(
            (self.scheme.as_str(), self.port),
            ("http", 80) | ("https", 443)
        );
        let host = if self.host.contains(':') {
            format!("[{}]", self.host)
        } else {
            self.host.clone()
        };
        if default {
            write!(f, "{}://{host}", self.scheme)
        } else {
            write!(f, "{}://{host}:{}", self.scheme, self.port)
        }
    }
}

/// Splits `host[:port]` (or `[v6]:port`) into a normalised host (lower
/// case, no trailing dot, addresses in their canonical form, no brackets)
/// and the port if given; `None` if malformed.
pub fn split_host(text: &str) -> Option<(String, Option<u16>)> {
    let (host, port) = if let Some(rest) = text.strip_prefix('[') {
        let (inside, after) = rest.split_once(']')?;
        let port = match after {
            "" => None,
            p => Some(p.strip_prefix(':')?.parse().ok()?),
        };
        (inside, port)
    } else {
        match text.split_once(':') {
            None => (text, None),
            Some((h, p)) if !p.contains(':') => (h, Some(p.parse().ok()?)),
            // A bare IPv6 address without brackets (not valid in Host, but
            // plain in a configuration list).
            Some(_) => (text, None),
        }
    };
    let host = host.trim_end_matches('.').to_ascii_lowercase();
    if host.is_empty()
        || !host
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_' | ':'))
    {
        return None;
    }
    let host = match host.parse::<IpAddr>() {
        Ok(ip) => ip.to_string(),
        Err(_) if host.contains(':') => return None,
        Err(_) => host,
    };
    Some((host, port))
}

/// Checks an `[http] allowed_hosts` entry: a name or address, no port.
pub fn parse_allowed_host(entry: &str) -> Result<String, String> {
    match split_host(entry) {
        Some((host, None)) => Ok(host),
        Some((_, Some(_))) => Err(format!(
            "[http] allowed_hosts entry \"{entry}\" has a port: give the name or address only (every port of it is allowed)"
        )),
        None => Err(format!(
            "[http] allowed_hosts entry \"{entry}\" is not a host name or an IP address"
        )),
    }
}

/// Checks an `[http] allowed_origins` entry: `http(s)://host[:port]`.
pub fn parse_allowed_origin(entry: &str) -> Result<String, String> {
    WebOrigin::parse(entry).map(|o| o.to_string()).ok_or_else(|| {
        format!(
            "[http] allowed_origins entry \"{entry}\" is not an origin: write it as a browser sends it, scheme, host and port only, e.g. \"https://hmi.plant.local:8443\" (\"null\" cannot be allowed)"
        )
    })
}
