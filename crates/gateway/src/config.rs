//! The gateway's configuration (docs/GATEWAY.md): sections `[identity]`, `[cloud]`,
//! `[state]`, `[bus]` (with `[[bus.nodes]]`), `[[networks]]`, `[privileges]`, `[limits]`,
//! `[policy]`.

use std::path::PathBuf;
use std::time::Duration;

use canbus::CanId;
use canopen::cob::restricted;
use nxg::gateway::{Identity, Policy, Settings};
use serde::{Deserialize, Serialize};

/// `[identity]`: what CONNECT says (NXg SW003 §5.2.1).
pub type IdentitySection = Identity;

/// `[cloud]`: where and how to connect.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CloudSection {
    /// `wss://HOST:PORT/ws` (TLS only).
    pub url: String,
    /// PEM file with the CA certificates to trust; absent: the system's roots.
    pub ca_file: Option<PathBuf>,
    /// PEM client certificate chain for mutual TLS.
    pub client_cert: Option<PathBuf>,
    /// PEM private key of the client certificate.
    pub client_key: Option<PathBuf>,
    /// `Origin` header of the upgrade request.
    pub origin: Option<String>,
    /// The portal's heartbeat interval (s); silence for 2 × this + 30 s drops the connection.
    pub heartbeat_s: u64,
    /// Seconds to wait for TCP, TLS and the upgrade each.
    pub connect_timeout_s: u64,
    /// Seconds to wait for CONNACK once CONNECT is sent. Longer than the others: a portal
    /// that answered TCP, TLS and the upgrade is admitting the gateway, and a gateway that gave
    /// up on it would throw that work away and come back with more (docs/GATEWAY.md
    /// §Behaviour, "Reconnect").
    pub connack_timeout_s: u64,
    /// Seconds between WebSocket pings.
    pub ping_s: u64,
    /// Local address to connect from (a gateway with several interfaces; `canlift loadgen`
    /// spreads its gateways over 127.0.0.x); absent: the system chooses.
    pub source_address: Option<std::net::IpAddr>,
    /// An HTTP proxy to reach the portal through (`http://[USER:PASSWORD@]HOST:PORT`, a
    /// `CONNECT` tunnel; TLS stays end to end); absent: `HTTPS_PROXY` and `NO_PROXY` decide.
    pub proxy: Option<String>,
}

impl CloudSection {
    /// The TLS client configuration: `ca_file` or the system's roots, the client certificate
    /// when there is one.
    pub fn tls(&self) -> Result<std::sync::Arc<rustls::ClientConfig>, tls::TlsError> {
        let identity = match (&self.client_cert, &self.client_key) {
            (Some(cert), Some(key)) => Some(tls::Identity { cert, key }),
            _ => None,
        };
        tls::client_config(self.ca_file.as_deref(), identity)
    }
}

impl Default for CloudSection {
    fn default() -> Self {
        CloudSection {
            url: String::new(),
            ca_file: None,
            client_cert: None,
            client_key: None,
            origin: None,
            heartbeat_s: 300,
            connect_timeout_s: 10,
            connack_timeout_s: 30,
            ping_s: 60,
            source_address: None,
            proxy: None,
        }
    }
}

/// `[state]`: durable state (the gateway's cloud token; the portal's database and development
/// PKI).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StateSection {
    /// Directory for durable state.
    pub dir: PathBuf,
}

impl Default for StateSection {
    fn default() -> Self {
        StateSection {
            dir: "state".into(),
        }
    }
}

/// `[[bus.nodes]]` / `[[networks.nodes]]`: what describes a node — the lift controller or any
/// other (docs/GATEWAY.md §Metadata).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NodeSection {
    /// Node-ID.
    pub id: u8,
    /// EDS or DCF file: which objects exist, their types, access and limits.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub eds: Option<PathBuf>,
    /// The vendor's NXg metadata (the catalog's format): names and hints per language, forms,
    /// units, privileges, lists.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub metadata: Option<PathBuf>,
    /// Its heartbeat period (ms) for supervision, instead of reading its 1017h; 0: do not
    /// supervise it (docs/PROTOCOL.md §Events).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub heartbeat_ms: Option<u16>,
    /// The node's SDO server channels the gateway may use (its 1201h ff., as the node's
    /// integrator assigned them to the gateway; its default channel only if listed): transfers
    /// to the node run on all of them at once instead of one after another on the default
    /// channel (CiA 301 §7.2.4.3: a channel serves one transfer at a time).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sdo_channels: Vec<SdoChannel>,
}

/// One SDO channel of a node: its 11-bit COB-IDs (`{ request = 0x6A1, response = 0x6C1 }`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SdoChannel {
    /// Client → server (the node's 1201h sub 1).
    pub request: u16,
    /// Server → client (the node's 1201h sub 2).
    pub response: u16,
}

impl SdoChannel {
    /// The channel's (request, response) identifiers, as the SDO client and server take them.
    pub const fn ids(&self) -> (CanId, CanId) {
        (
            CanId::Standard(self.request),
            CanId::Standard(self.response),
        )
    }
}

impl NodeSection {
    /// The node's SDO client channels for [`canopen::sdo::clients::SdoClients::with_channels`].
    pub fn client_channels(&self) -> impl Iterator<Item = (u8, CanId, CanId)> + '_ {
        self.sdo_channels.iter().map(|c| {
            let (request, response) = c.ids();
            (self.id, request, response)
        })
    }

    /// Each channel's identifiers are 11-bit, used once on the network (`taken` holds those
    /// of the nodes checked before) and not restricted (CiA 301 §7.3.5) — except the node's
    /// own default channel, 600h/580h + node-ID.
    fn check_sdo_channels(&self, taken: &mut Vec<u16>) -> Result<(), ConfigError> {
        for c in &self.sdo_channels {
            let refuse = |why: &str| {
                Err(ConfigError(format!(
                    "node {}: sdo_channels {{ request = {:#X}, response = {:#X} }}: {why}",
                    self.id, c.request, c.response
                )))
            };
            let allowed = |id: u16, default: u16| {
                id == default + u16::from(self.id) || (id <= 0x7FF && !restricted(id))
            };
            if !allowed(c.request, 0x600) || !allowed(c.response, 0x580) {
                return refuse(
                    "not an 11-bit identifier free for SDO (CiA 301 §7.3.5 restricts 581h–5FFh, \
                     601h–67Fh but for the node's own default channel, 6E0h–7FFh and others)",
                );
            }
            if c.request == c.response || taken.contains(&c.request) || taken.contains(&c.response)
            {
                return refuse("an identifier is used twice");
            }
            taken.extend([c.request, c.response]);
        }
        Ok(())
    }

    /// Node `id`, nothing said about it yet.
    pub fn new(id: u8) -> NodeSection {
        NodeSection {
            id,
            eds: None,
            metadata: None,
            heartbeat_ms: None,
            sdo_channels: Vec::new(),
        }
    }

    /// A node described by `eds` alone.
    pub fn with_eds(id: u8, eds: PathBuf) -> NodeSection {
        NodeSection {
            eds: Some(eds),
            ..NodeSection::new(id)
        }
    }
}

/// `[bus]`: network 1, where the gateway is a node.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BusSection {
    /// Bus URL.
    pub url: String,
    /// The gateway's own node-ID.
    pub node_id: u8,
    /// Node-ID of the lift controller.
    pub lift_controller: u8,
    /// SDO response timeout (ms).
    pub sdo_timeout_ms: u64,
    /// How often configured SDO channels are asked again (1000h) while their node answers on
    /// none, and a channel set aside is asked whether it answers again (ms).
    pub sdo_probe_ms: u64,
    /// How often subscribed objects that no PDO carries are read (ms).
    pub poll_ms: u64,
    /// Nodes with an EDS.
    pub nodes: Vec<NodeSection>,
}

impl Default for BusSection {
    fn default() -> Self {
        BusSection {
            url: "socketcand://127.0.0.1:29536/can0".into(),
            node_id: 9,
            lift_controller: 1,
            sdo_timeout_ms: 1000,
            sdo_probe_ms: 10_000,
            poll_ms: 500,
            nodes: Vec::new(),
        }
    }
}

/// `[[networks]]`: further CAN networks reached through the gateway.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NetworkSection {
    /// The `net` number requests use (2–255).
    pub net: u8,
    /// Bus URL.
    pub url: String,
    /// Nodes with an EDS.
    #[serde(default)]
    pub nodes: Vec<NodeSection>,
}

/// `[privileges]`: the passwords (as SHA-1 hex) elevation compares against.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PrivilegesSection {
    /// SHA-1 hex of the service password; absent: service rights cannot be granted.
    pub service_sha1: Option<String>,
    /// SHA-1 hex of the setup password.
    pub setup_sha1: Option<String>,
    /// Seconds a grant lasts.
    pub duration_s: u64,
    /// Seconds the third wrong hash for a level locks its elevation (doubling with each
    /// further one, up to an hour).
    pub lockout_s: u64,
}

impl Default for PrivilegesSection {
    fn default() -> Self {
        PrivilegesSection {
            service_sha1: None,
            setup_sha1: None,
            duration_s: 300,
            lockout_s: 30,
        }
    }
}

/// `[limits]`: what one connection may use.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LimitsSection {
    /// Largest WebSocket message accepted (bytes); larger ones close the connection.
    pub max_message_bytes: usize,
    /// Requests running on the bus at once.
    pub max_in_flight: usize,
    /// Requests waiting behind them before new ones are refused as busy.
    pub max_queued: usize,
    /// Subscriptions per connection.
    pub max_subscriptions: usize,
    /// Bus events kept while no portal takes them (the oldest go first, counted in the log).
    pub max_queued_events: usize,
}

impl Default for LimitsSection {
    fn default() -> Self {
        LimitsSection {
            max_message_bytes: 65536,
            max_in_flight: 16,
            max_queued: 256,
            max_subscriptions: 1024,
            max_queued_events: nxg::gateway::QUEUED_EVENTS,
        }
    }
}

/// The whole configuration.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Config {
    /// `[identity]`.
    pub identity: IdentitySection,
    /// `[cloud]`.
    pub cloud: CloudSection,
    /// `[state]`.
    pub state: StateSection,
    /// `[bus]`.
    pub bus: BusSection,
    /// `[[networks]]`.
    pub networks: Vec<NetworkSection>,
    /// `[privileges]`.
    pub privileges: PrivilegesSection,
    /// `[limits]`.
    pub limits: LimitsSection,
    /// `[policy]`: what the cloud may write and see.
    pub policy: Policy,
    /// `[metrics]`: the gateway's own metrics.
    pub metrics: MetricsSection,
}

/// `[metrics]` (docs/GATEWAY.md §Metrics).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MetricsSection {
    /// Serve `GET /metrics` in plain HTTP here (a loopback or management address); absent:
    /// no listener, no metrics kept.
    pub listen: Option<std::net::SocketAddr>,
}

/// A configuration that cannot work.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("configuration: {0}")]
pub struct ConfigError(pub String);

fn sha1_hex(name: &str, value: &Option<String>) -> Result<(), ConfigError> {
    match value {
        Some(v) if v.len() != 40 || !v.bytes().all(|b| b.is_ascii_hexdigit()) => Err(ConfigError(
            format!("privileges.{name} must be 40 hex digits (a SHA-1)"),
        )),
        _ => Ok(()),
    }
}

impl Config {
    /// A configuration for the gateway `identity` on `bus`, connecting to `portal`
    /// (`wss://…/ws`) trusting `ca`, keeping its state in `state`; everything else default.
    pub fn for_portal(
        identity: Identity,
        portal: &str,
        ca: &std::path::Path,
        bus: &str,
        state: &std::path::Path,
    ) -> Config {
        let mut c = Config {
            identity,
            ..Config::default()
        };
        c.cloud.url = portal.into();
        c.cloud.ca_file = Some(ca.to_path_buf());
        c.state.dir = state.to_path_buf();
        c.bus.url = bus.into();
        c
    }

    /// Check what can be checked before connecting.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let err = |m: &str| Err(ConfigError(m.into()));
        if self.identity.sernum.is_empty() {
            return err("identity.sernum is required");
        }
        if !self.cloud.url.starts_with("wss://") {
            return err("cloud.url must be wss://HOST:PORT/PATH (the connector is TLS only)");
        }
        if self.cloud.client_cert.is_some() != self.cloud.client_key.is_some() {
            return err("cloud.client_cert and cloud.client_key come together");
        }
        sha1_hex("service_sha1", &self.privileges.service_sha1)?;
        sha1_hex("setup_sha1", &self.privileges.setup_sha1)?;
        if !(1..=127).contains(&self.bus.node_id) || !(1..=127).contains(&self.bus.lift_controller)
        {
            return err("bus.node_id and bus.lift_controller are node-IDs 1–127");
        }
        let mut nets = vec![1u8];
        for n in &self.networks {
            if nets.contains(&n.net) {
                return err("each [[networks]] has its own net number (1 is [bus])");
            }
            nets.push(n.net);
        }
        for (_, nodes) in self.node_sections() {
            let mut taken = Vec::new();
            for n in nodes {
                if !(1..=127).contains(&n.id) {
                    return err("[[bus.nodes]] and [[networks.nodes]]: id is a node-ID 1–127");
                }
                if n.eds.is_none()
                    && n.metadata.is_none()
                    && n.heartbeat_ms.is_none()
                    && n.sdo_channels.is_empty()
                {
                    return Err(ConfigError(format!(
                        "node {}: give eds, metadata, heartbeat_ms or sdo_channels",
                        n.id
                    )));
                }
                n.check_sdo_channels(&mut taken)?;
            }
        }
        if self.limits.max_in_flight == 0 || self.limits.max_message_bytes < 1024 {
            return err("limits.max_in_flight ≥ 1 and limits.max_message_bytes ≥ 1024");
        }
        if self.privileges.lockout_s == 0 {
            return err("privileges.lockout_s ≥ 1");
        }
        if !(1..=nxg::msg::API).contains(&self.identity.api) {
            return Err(ConfigError(format!(
                "identity.api is 1–{}, the NXg API versions canlift speaks (bus events need no \
                 API number: docs/PROTOCOL.md §Events)",
                nxg::msg::API
            )));
        }
        if self.policy.default_privilege > 3 {
            return err(
                "policy.default_privilege is 0 (user), 1 (service), 2 (setup) or 3 (never)",
            );
        }
        Ok(())
    }

    /// Each network's described nodes: `[[bus.nodes]]` as net 1, then each `[[networks]]`'s.
    pub fn node_sections(&self) -> impl Iterator<Item = (u8, &[NodeSection])> {
        std::iter::once((1u8, self.bus.nodes.as_slice()))
            .chain(self.networks.iter().map(|n| (n.net, n.nodes.as_slice())))
    }

    /// The session settings.
    pub fn settings(&self) -> Settings {
        let mut nets = vec![1];
        nets.extend(self.networks.iter().map(|n| n.net));
        Settings {
            identity: Identity {
                api: self.identity.api.clamp(1, nxg::msg::API),
                ..self.identity.clone()
            },
            service_sha1: self.privileges.service_sha1.clone(),
            setup_sha1: self.privileges.setup_sha1.clone(),
            privilege_duration: Duration::from_secs(self.privileges.duration_s),
            max_in_flight: self.limits.max_in_flight,
            max_queued: self.limits.max_queued,
            max_subscriptions: self.limits.max_subscriptions,
            heartbeat: Duration::from_secs(self.cloud.heartbeat_s.max(1)),
            connack_timeout: Duration::from_secs(self.cloud.connack_timeout_s.max(1)),
            lift_controller: self.bus.lift_controller,
            nets,
            policy: self.policy.clone(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_channels(sections: &[(u8, &[(u16, u16)])]) -> Config {
        let mut config = Config::default();
        config.identity.sernum = "test".into();
        config.cloud.url = "wss://127.0.0.1:1/".into();
        config.bus.nodes = sections
            .iter()
            .map(|&(id, channels)| NodeSection {
                sdo_channels: channels
                    .iter()
                    .map(|&(request, response)| SdoChannel { request, response })
                    .collect(),
                ..NodeSection::with_eds(id, "unused.eds".into())
            })
            .collect();
        config
    }

    #[test]
    fn sdo_channels_need_free_identifiers() {
        let ok = with_channels(&[
            (1, &[(0x601, 0x581), (0x6A1, 0x6C1)]),
            (12, &[(0x6A2, 0x6C2)]),
        ]);
        assert_eq!(ok.validate(), Ok(()));
        assert_eq!(
            ok.bus.nodes[0].client_channels().collect::<Vec<_>>(),
            vec![
                (1, CanId::Standard(0x601), CanId::Standard(0x581)),
                (1, CanId::Standard(0x6A1), CanId::Standard(0x6C1)),
            ]
        );
        for (sections, why) in [
            (
                &[(1u8, &[(0x60C, 0x58C)][..])][..],
                "another node's default channel",
            ),
            (
                &[(1, &[(0x601, 0x58C)][..])][..],
                "another node's default response",
            ),
            (&[(1, &[(0x705, 0x6C1)][..])][..], "heartbeat of node 5"),
            (&[(1, &[(0x800, 0x6C1)][..])][..], "not 11-bit"),
            (&[(1, &[(0x6A1, 0x6A1)][..])][..], "request = response"),
            (
                &[(1, &[(0x6A1, 0x6C1)][..]), (12, &[(0x6A2, 0x6C1)][..])][..],
                "one response for two nodes",
            ),
        ] {
            assert!(with_channels(sections).validate().is_err(), "{why}");
        }
        // Another network may use the same identifiers.
        let mut two = with_channels(&[(1, &[(0x6A1, 0x6C1)])]);
        two.networks = vec![NetworkSection {
            net: 2,
            url: "mem://other".into(),
            nodes: two.bus.nodes.clone(),
        }];
        assert_eq!(two.validate(), Ok(()));
    }
}
