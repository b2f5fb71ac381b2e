//! Node addresses: `HOST:PORT` parsed, normalised and compared (localhost is 127.0.0.1 and ::1).

/// Checks `host:port` (or `[v6]:port`): a valid port (1..=65535) and a plausible host name or IP
/// literal. Names are not resolved.
pub fn check_address(address: &str) -> Result<(), String> {
    parse_address(address).map(|_| ())
}

/// Where a node address leads, as far as the text says (the model does no I/O, so names other
/// than `localhost` are not resolved): an IP address (an IPv4-mapped IPv6 address as the IPv4
/// one), the loopback name (`localhost` and `*.localhost`, RFC 6761: 127.0.0.1 and ::1), or a
/// host name without regard to case or a final dot; and the port.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum AddressHost {
    Ip(std::net::IpAddr),
    Localhost,
    Name(String),
}

/// A node address, parsed: [`AddressHost`] and port.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct NodeAddress {
    pub host: AddressHost,
    pub port: u16,
}

impl NodeAddress {
    /// Whether two addresses lead to the same socket: the same port, and the same IP address,
    /// the same name, or `localhost` and 127.0.0.1 or ::1.
    pub fn same_place(&self, other: &NodeAddress) -> bool {
        let loopback = |ip: &std::net::IpAddr| match ip {
            std::net::IpAddr::V4(v4) => *v4 == std::net::Ipv4Addr::LOCALHOST,
            std::net::IpAddr::V6(v6) => *v6 == std::net::Ipv6Addr::LOCALHOST,
        };
        self.port == other.port
            && match (&self.host, &other.host) {
                (AddressHost::Localhost, AddressHost::Ip(ip))
                | (AddressHost::Ip(ip), AddressHost::Localhost) => loopback(ip),
                (a, b) => a == b,
            }
    }
}

/// Parses `host:port` (or `[v6]:port`), as [`check_address`] checks it.
pub fn parse_address(address: &str) -> Result<NodeAddress, String> {
    use std::net::IpAddr;
    let ip_host = |ip: IpAddr| -> Result<AddressHost, String> {
        let ip = match ip {
            IpAddr::V6(v6) => v6.to_ipv4_mapped().map_or(IpAddr::V6(v6), IpAddr::V4),
            v4 => v4,
        };
        if ip.is_unspecified() {
            return Err(format!(
                "'{address}': {ip} is the unspecified address, which no controller or peer can reach: \
                 give the node's own address"
            ));
        }
        Ok(AddressHost::Ip(ip))
    };
    if let Some(rest) = address.strip_prefix('[') {
        let Some((host, port)) = rest.split_once("]:") else {
            return Err(format!("'{address}' is not [IPv6]:port"));
        };
        let ip =
            host.parse::<std::net::Ipv6Addr>().map_err(|_| format!("'{host}' is not an IPv6 address"))?;
        return Ok(NodeAddress { host: ip_host(IpAddr::V6(ip))?, port: parse_port(address, port)? });
    }
    let Some((host, port)) = address.rsplit_once(':') else {
        return Err(format!("'{address}' is not host:port (the port is missing)"));
    };
    if host.is_empty() {
        return Err(format!("'{address}' has no host"));
    }
    if host.contains(':') {
        return Err(format!("'{address}': write an IPv6 address in brackets, [addr]:port"));
    }
    let port = parse_port(address, port)?;
    if let Ok(ip) = host.parse::<std::net::Ipv4Addr>() {
        return Ok(NodeAddress { host: ip_host(IpAddr::V4(ip))?, port });
    }
    let label_ok = |l: &str| {
        !l.is_empty()
            && l.len() <= 63
            && l.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
            && !l.starts_with('-')
            && !l.ends_with('-')
    };
    let name = host.strip_suffix('.').unwrap_or(host).to_ascii_lowercase();
    if host.len() > 253 || !name.split('.').all(label_ok) {
        return Err(format!("'{host}' is not a valid host name or IP address"));
    }
    let host = if name == "localhost" || name.ends_with(".localhost") {
        AddressHost::Localhost
    } else {
        AddressHost::Name(name)
    };
    Ok(NodeAddress { host, port })
}

pub(crate) fn parse_port(address: &str, port: &str) -> Result<u16, String> {
    match port.parse::<u16>() {
        Ok(p) if p > 0 => Ok(p),
        _ => Err(format!("'{address}': port '{port}' is not in 1..=65535")),
    }
}

/// The keys under which an address's place can be found among others' `(host, port)`: its own,
/// and for the loopback the other spellings that [`NodeAddress::same_place`] takes as the same
/// (`localhost` for 127.0.0.1 and ::1, and both of those for `localhost`).
pub(crate) fn same_place_keys(a: &NodeAddress) -> Vec<(AddressHost, u16)> {
    use std::net::{IpAddr, Ipv4Addr, Ipv6Addr};
    let mut keys = vec![(a.host.clone(), a.port)];
    match &a.host {
        AddressHost::Localhost => {
            keys.push((AddressHost::Ip(IpAddr::V4(Ipv4Addr::LOCALHOST)), a.port));
            keys.push((AddressHost::Ip(IpAddr::V6(Ipv6Addr::LOCALHOST)), a.port));
        }
        AddressHost::Ip(ip) if *ip == Ipv4Addr::LOCALHOST || *ip == Ipv6Addr::LOCALHOST => {
            keys.push((AddressHost::Localhost, a.port));
        }
        _ => {}
    }
    keys
}
