//! `isowalld run --peer-addr NODE=HOST:PORT`: where this node reaches a peer, in place of the
//! peer's `address` in the wall config (object space sends pixels node to node). For nodes behind
//! NAT, a relay or a port forward, and for tests that put a lossy relay between daemons. Only the
//! address changes: the peer is still checked by its certificate's node name.

use anyhow::{anyhow, Result};
use isowall_model::config::WallConfig;

/// One `NODE=HOST:PORT` override.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PeerAddr {
    pub node: String,
    pub address: String,
}

/// Parses `NODE=HOST:PORT` (the flag's value parser; the node is checked against the config in
/// [`apply`], the address resolved there too).
pub fn parse(s: &str) -> Result<PeerAddr, String> {
    let (node, address) = s
        .split_once('=')
        .ok_or_else(|| format!("expected NODE=HOST:PORT, e.g. node1=10.0.0.7:7442, got '{s}'"))?;
    let (node, address) = (node.trim(), address.trim());
    if node.is_empty() {
        return Err(format!("'{s}': the node name before '=' is empty"));
    }
    if address.rsplit_once(':').is_none_or(|(host, port)| host.is_empty() || port.parse::<u16>().is_err()) {
        return Err(format!("'{s}': '{address}' is not HOST:PORT"));
    }
    Ok(PeerAddr { node: node.to_string(), address: address.to_string() })
}

/// Replaces the named peers' addresses in `config` (this node's copy). Errors name the flag's
/// value and why: a node the config does not have, this node itself (its own address is where it
/// listens), a node given twice, an address that does not resolve.
pub fn apply(config: &mut WallConfig, own: &str, overrides: &[PeerAddr]) -> Result<()> {
    let names: Vec<String> = config.nodes.iter().map(|n| n.name.clone()).collect();
    for (i, o) in overrides.iter().enumerate() {
        let flag = format!("--peer-addr {}={}", o.node, o.address);
        if o.node == own {
            return Err(anyhow!(
                "{flag}: '{own}' is this node; its own address (where it listens) is the config's"
            ));
        }
        if overrides[..i].iter().any(|p| p.node == o.node) {
            return Err(anyhow!("{flag}: node '{}' is given more than once", o.node));
        }
        let Some(node) = config.nodes.iter_mut().find(|n| n.name == o.node) else {
            return Err(anyhow!(
                "{flag}: no node '{}' in the wall config (nodes: {})",
                o.node,
                names.join(", ")
            ));
        };
        isowall_net::transport::resolve(&o.address).map_err(|e| anyhow!("{flag}: {e}"))?;
        tracing::info!(peer = %o.node, config = %node.address, address = %o.address, "peer address overridden");
        node.address = o.address.clone();
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> WallConfig {
        let text = "[wall]\nname = \"w\"\n\n[camera]\neye = [1, 2, 3]\ntarget = [0, 0, 0]\n\n\
                    [volume]\nsource = \"procedural:sphere:16\"\n\n[certificates]\ndir = \"keys\"\n\n\
                    [[tiles]]\nname = \"t0\"\nx = 0\ny = 0\nwidth = 8\nheight = 8\n\n\
                    [[tiles]]\nname = \"t1\"\nx = 8\ny = 0\nwidth = 8\nheight = 8\n\n\
                    [[nodes]]\nname = \"node0\"\naddress = \"127.0.0.1:7441\"\ntiles = [\"t0\"]\n\n\
                    [[nodes]]\nname = \"node1\"\naddress = \"127.0.0.1:7442\"\ntiles = [\"t1\"]\n";
        WallConfig::parse(text, std::path::Path::new("w.toml")).expect("a valid config")
    }

    #[test]
    fn parses_node_and_address() {
        assert_eq!(
            parse("node1=127.0.0.1:9000").unwrap(),
            PeerAddr { node: "node1".into(), address: "127.0.0.1:9000".into() }
        );
        assert_eq!(parse("n=[::1]:9").unwrap().address, "[::1]:9");
        for bad in ["node1", "=1.2.3.4:5", "node1=1.2.3.4", "node1=1.2.3.4:x", "node1=:80"] {
            assert!(parse(bad).is_err(), "{bad} accepted");
        }
    }

    #[test]
    fn overrides_a_peer_and_refuses_unknown_own_and_repeated_nodes() {
        let mut c = config();
        let o = |n: &str, a: &str| PeerAddr { node: n.into(), address: a.into() };
        apply(&mut c, "node0", &[o("node1", "127.0.0.1:9000")]).unwrap();
        assert_eq!(c.node("node1").unwrap().address, "127.0.0.1:9000");
        assert_eq!(c.node("node0").unwrap().address, "127.0.0.1:7441");
        let e = apply(&mut config(), "node0", &[o("node7", "127.0.0.1:1")]).unwrap_err().to_string();
        assert!(e.contains("no node 'node7'") && e.contains("nodes: node0, node1"), "{e}");
        let e = apply(&mut config(), "node0", &[o("node0", "127.0.0.1:1")]).unwrap_err().to_string();
        assert!(e.contains("is this node"), "{e}");
        let twice = [o("node1", "127.0.0.1:1"), o("node1", "127.0.0.1:2")];
        let e = apply(&mut config(), "node0", &twice).unwrap_err().to_string();
        assert!(e.contains("more than once"), "{e}");
    }
}
