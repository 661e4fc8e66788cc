//! The elevator gateway: the device side of the NXg CANopen-Lift Connector (NXg SW003 §5–§7,
//! docs/PROTOCOL.md). It dials out to the portal over TLS WebSocket, answers its JSON-RPC requests
//! from the lift's object dictionaries and pushes subscribed changes; when the connection ends it
//! comes back with capped, fully jittered backoff.
//!
//! Two modes, one engine ([`nxg::gateway::Session`]):
//! - *bus-node mode* ([`Gateway::bus_node`]): the gateway is a node (9 by default) on the
//!   CANopen-Lift bus and reaches the lift controller and other nodes by SDO; subscriptions are
//!   fed by the controller's TPDOs and by SDO polling;
//! - *embedded mode* ([`Gateway::embedded`]): a controller written in Rust hands the gateway its
//!   own dictionary; reads and writes are local, changes notify at once.

#![warn(missing_docs)]

pub mod access;
pub mod config;
pub mod connection;
pub mod feed;
pub mod fleet;
pub mod lockout;
pub mod metadata;
pub mod metrics;
pub mod supervision;
pub mod token;

use std::collections::HashMap;
use std::sync::{Arc, PoisonError};
use std::time::{Duration, Instant};

use canbus::backoff::Backoff;
use canbus::{Bus, Interface};
use canopen::node::{LocalNode, NodeConfig};
use canopen::od::ObjectDictionary;
use canopen::od::SharedDictionary;
use canopen::sdo::client::ClientConfig;
use canopen::sdo::clients::SdoClients;
use nxg::gateway::{Context, Target};
use tokio::sync::{mpsc, watch};
use tracing::Instrument;

use crate::access::Objects;
use crate::config::{Config, NodeSection};
use crate::feed::{Feed, LocalChanges, Update};
use crate::metadata::BusMetadata;
use crate::token::TokenStore;

/// Why the gateway cannot start.
#[derive(Debug, thiserror::Error)]
pub enum GatewayError {
    /// The configuration is inconsistent.
    #[error(transparent)]
    Config(#[from] config::ConfigError),
    /// TLS could not be set up.
    #[error(transparent)]
    Tls(#[from] tls::TlsError),
    /// A bus could not be opened.
    #[error("bus {url}: {error}")]
    Bus {
        /// The URL.
        url: String,
        /// Why.
        error: canbus::BusError,
    },
    /// An EDS could not be read.
    #[error(transparent)]
    Eds(#[from] canopen::eds::EdsError),
    /// A vendor metadata file is malformed (`FILE:LINE: reason`).
    #[error("{0}")]
    Metadata(String),
    /// The metrics could not be set up.
    #[error(transparent)]
    Metrics(#[from] metrics::MetricsError),
}

enum Mode {
    Bus {
        sdo: SdoClients,
        bus: Interface,
    },
    Local {
        od: SharedDictionary,
        changes: LocalChanges,
    },
}

/// What every connection of a gateway shares.
pub struct Shared {
    config: Config,
    /// Replaced by [`TlsReload`]: each connection takes the one current when it begins.
    tls: std::sync::RwLock<Arc<rustls::ClientConfig>>,
    token: TokenStore,
    context: Context,
    lockout: lockout::LockoutStore,
    objects: Objects,
    /// The lift-safety interlock every remote write passes (none: `[policy] lift_state = ""`).
    interlock: Option<access::Interlock>,
    mode: Mode,
    /// Whether a connection is in service (CONNACK came), for [`Gateway::online`].
    online: watch::Sender<bool>,
    /// Woken when bus events were queued for the portal.
    events_ready: Arc<tokio::sync::Notify>,
    /// The gateway's metrics, with `[metrics] listen` (none otherwise: a load generator's
    /// thousands of gateways keep no registry each).
    metrics: Option<Arc<metrics::GatewayMetrics>>,
}

impl Shared {
    fn controller(&self) -> Target {
        Target {
            net: 1,
            node: self.config.bus.lift_controller,
        }
    }

    async fn feed(&self, tx: mpsc::Sender<Update>) -> Feed {
        match &self.mode {
            Mode::Bus { sdo, bus } => {
                Feed::bus(
                    self.objects.clone(),
                    Some(sdo.clone()),
                    Some(bus.clone()),
                    self.controller(),
                    Duration::from_millis(self.config.bus.poll_ms.max(50)),
                    tx,
                )
                .await
            }
            Mode::Local { od, changes } => Feed::local(changes, od.clone(), self.controller(), tx),
        }
    }
}

/// A configured gateway.
pub struct Gateway {
    shared: Arc<Shared>,
    node: Option<LocalNode>,
    /// The watch over each network (bus-node mode).
    supervisors: Vec<tokio::task::JoinHandle<()>>,
}

/// Open the bus behind `url` once: the gateway's endpoints on it (SDO client, its own node,
/// supervision, a PDO feed per portal connection) share one link.
async fn open(url: &str) -> Result<Interface, GatewayError> {
    Interface::open(url)
        .await
        .map_err(|error| bus_error(url, error))
}

fn endpoint(bus: &Interface) -> Result<Bus, GatewayError> {
    bus.endpoint()
        .map_err(|error| bus_error(&bus.url().to_string(), error))
}

fn bus_error(url: &str, error: canbus::BusError) -> GatewayError {
    GatewayError::Bus {
        url: url.to_owned(),
        error,
    }
}

/// Reads `[cloud]`'s CA file and client certificate again (`canlift gateway` on SIGHUP;
/// docs/OPERATIONS.md §Certificates): the next connection uses them, the one in service goes on,
/// and the TLS session cache carries over (a resumption needs no new certificate check).
#[derive(Clone)]
pub struct TlsReload(Arc<Shared>);

impl TlsReload {
    /// Read the files; on an error the configuration in use stays.
    pub fn reload(&self) -> Result<(), GatewayError> {
        let mut fresh = Arc::unwrap_or_clone(self.0.config.cloud.tls()?);
        let mut current = self.0.tls.write().unwrap_or_else(PoisonError::into_inner);
        fresh.resumption = current.resumption.clone();
        *current = Arc::new(fresh);
        Ok(())
    }
}

impl Gateway {
    /// Bus-node mode: join `[bus]` as node `bus.node_id` (heartbeat, identity) and reach the
    /// nodes of every network by SDO.
    pub async fn bus_node(config: Config) -> Result<Gateway, GatewayError> {
        config.validate()?;
        // The description files first: a malformed one stops the gateway at once.
        let metadata = BusMetadata::load(&config)?;
        let tls = config.cloud.tls()?;
        let client = ClientConfig {
            timeout: Duration::from_millis(config.bus.sdo_timeout_ms.max(10)),
            ..ClientConfig::default()
        };
        let bus = open(&config.bus.url).await?;
        let mut interfaces = HashMap::from([(1u8, bus.clone())]);
        for n in &config.networks {
            interfaces.insert(n.net, open(&n.url).await?);
        }
        let mut nets = HashMap::new();
        // Configured SDO channels a node does not serve are named in the log once it answers.
        let mut checks = Vec::new();
        let probe = Duration::from_millis(config.bus.sdo_probe_ms.max(10));
        for (net, nodes) in config.node_sections() {
            let Some(interface) = interfaces.get(&net) else {
                continue;
            };
            let channels: Vec<_> = nodes
                .iter()
                .flat_map(NodeSection::client_channels)
                .collect();
            let sdo = SdoClients::with_channels(endpoint(interface)?, client.clone(), &channels);
            sdo.set_probe_interval(probe);
            for n in nodes.iter().filter(|n| !n.sdo_channels.is_empty()) {
                let check = supervision::check_sdo_channels(sdo.clone(), net, n.id, probe);
                checks.push(tokio::spawn(async move {
                    check.await;
                }));
            }
            nets.insert(net, sdo);
        }
        // [bus] is net 1 (the configuration refuses it for [[networks]]).
        let sdo = nets[&1].clone();
        let node_config = NodeConfig {
            device_type: 417,
            identity: [config.identity.vendorid, config.identity.productcode, 1, 0],
            device_name: "canlift elevator gateway".into(),
            hardware_version: config.identity.hardware.clone(),
            software_version: config.identity.software.clone(),
            heartbeat_ms: 1000,
            pdos: (0, 0),
            ..NodeConfig::new(config.bus.node_id)
        };
        let node = LocalNode::start(endpoint(&bus)?, ObjectDictionary::new(), node_config);
        node.nmt(canopen::nmt::NmtCommand::Start);
        let mut networks = Vec::new();
        for (net, nodes) in config.node_sections() {
            // The gateway is a node of [bus] only.
            let own = if net == 1 { config.bus.node_id } else { 0 };
            let (Some(sdo), Some(interface)) = (nets.get(&net).cloned(), interfaces.get(&net))
            else {
                continue;
            };
            networks.push(supervision::Network {
                net,
                bus: endpoint(interface)?,
                sdo,
                own,
                configured: nodes
                    .iter()
                    .filter_map(|n| n.heartbeat_ms.map(|ms| (n.id, ms)))
                    .collect(),
            });
        }
        let mode = Mode::Bus { sdo, bus };
        let mut gateway =
            Gateway::assemble(config, tls, metadata, Objects::Bus(nets), mode, Some(node))?;
        let sink = supervision::Sink {
            queue: gateway.shared.context.events.clone(),
            ready: gateway.shared.events_ready.clone(),
        };
        gateway.supervisors = networks
            .into_iter()
            .map(|n| supervision::spawn(n, sink.clone()))
            .collect();
        gateway.supervisors.extend(checks);
        Ok(gateway)
    }

    /// Embedded mode: serve `od`, the dictionary of the controller the gateway is linked into
    /// (node `bus.lift_controller`); metadata as in bus-node mode (docs/GATEWAY.md §Metadata).
    pub fn embedded(config: Config, od: SharedDictionary) -> Result<Gateway, GatewayError> {
        let tls = config.cloud.tls()?;
        let description = Arc::new(od.lock().unwrap_or_else(PoisonError::into_inner).clone());
        Gateway::embedded_with_tls(config, od, description, tls)
    }

    /// [`Gateway::embedded`] with the caller's TLS client configuration instead of one made
    /// from `[cloud]` — one that outlives the gateway keeps its session tickets, so a gateway
    /// made again resumes its TLS session (`canlift loadgen`'s fleets, the reconnect storm of
    /// docs/BENCHMARKS.md) — and with `description`, the controller's dictionary as its EDS
    /// would describe it (objects, types, access, limits), which gateways in front of the same
    /// controller share.
    pub fn embedded_with_tls(
        config: Config,
        od: SharedDictionary,
        description: Arc<ObjectDictionary>,
        tls: Arc<rustls::ClientConfig>,
    ) -> Result<Gateway, GatewayError> {
        config.validate()?;
        // The controller's own dictionary is its EDS, unless the configuration names one.
        let metadata = BusMetadata::load(&config)?.with_dictionary(
            Target {
                net: 1,
                node: config.bus.lift_controller,
            },
            description,
        );
        let objects = Objects::Local {
            od: od.clone(),
            node: config.bus.lift_controller,
        };
        let mode = Mode::Local {
            changes: LocalChanges::install(&od),
            od,
        };
        Gateway::assemble(config, tls, metadata, objects, mode, None)
    }

    fn assemble(
        config: Config,
        tls: Arc<rustls::ClientConfig>,
        metadata: BusMetadata,
        objects: Objects,
        mode: Mode,
        node: Option<LocalNode>,
    ) -> Result<Gateway, GatewayError> {
        tracing::info!(policy = %config.policy.summary(), "write policy");
        for why in config.policy.ineffective() {
            tracing::warn!("write policy: {why}");
        }
        let metrics = match config.metrics.listen {
            Some(_) => Some(Arc::new(metrics::GatewayMetrics::new()?)),
            None => None,
        };
        let lockout = lockout::LockoutStore::new(
            &config.state.dir,
            Duration::from_secs(config.privileges.lockout_s),
        );
        let mut context = Context::new(Arc::new(metadata));
        context.lockout = Arc::new(std::sync::Mutex::new(lockout.load()));
        context.events = Arc::new(std::sync::Mutex::new(nxg::gateway::EventQueue::new(
            config.limits.max_queued_events,
        )));
        let interlock = access::Interlock::new(
            &config.policy,
            Target {
                net: 1,
                node: config.bus.lift_controller,
            },
        );
        Ok(Gateway {
            shared: Arc::new(Shared {
                interlock,
                token: TokenStore::new(&config.state.dir),
                context,
                lockout,
                config,
                tls: std::sync::RwLock::new(tls),
                objects,
                mode,
                online: watch::channel(false).0,
                events_ready: Arc::default(),
                metrics,
            }),
            node,
            supervisors: Vec::new(),
        })
    }

    /// What reloads the CA and client certificate of `[cloud]` while the gateway runs.
    pub fn tls_reload(&self) -> TlsReload {
        TlsReload(self.shared.clone())
    }

    /// Whether the gateway is connected to the portal and in service (CONNACK received) —
    /// for a status LED, a health check, or `canlift loadgen`'s count.
    pub fn online(&self) -> watch::Receiver<bool> {
        self.shared.online.subscribe()
    }

    /// Connect, serve, and reconnect until `shutdown` turns true.
    pub async fn run(mut self, mut shutdown: watch::Receiver<bool>) {
        if let (Some(listen), Some(metrics)) = (
            self.shared.config.metrics.listen,
            self.shared.metrics.clone(),
        ) {
            self.supervisors.push(tokio::spawn(async move {
                if let Err(e) = metrics::serve(listen, metrics).await {
                    tracing::error!(%listen, error = %e, "metrics listener failed");
                }
            }));
        }
        // docs/PROTOCOL.md: 1 s growing to 5 min, full jitter, reset after a stable minute.
        let mut backoff = Backoff::new(Duration::from_secs(1), Duration::from_secs(300));
        for number in 1u64.. {
            if *shutdown.borrow() {
                break;
            }
            let started = Instant::now();
            // Every log line of a connection names it (refused puts, elevation).
            let span = tracing::info_span!("connection", n = number);
            let ended = connection::run(&self.shared, &mut shutdown)
                .instrument(span)
                .await;
            self.shared.online.send_replace(false);
            if let Some(metrics) = &self.shared.metrics {
                metrics.connected.set(0);
                if ended.served {
                    metrics.disconnects.inc();
                }
            }
            if ended.shutdown {
                break;
            }
            if ended.served && started.elapsed() >= Duration::from_secs(60) {
                backoff.reset();
            }
            let delay = backoff.next_delay();
            tracing::warn!(cause = %ended.cause, retry_in_ms = delay.as_millis() as u64, "connection ended");
            tokio::select! {
                _ = tokio::time::sleep(delay) => {}
                _ = shutdown.changed() => break,
            }
        }
        for supervisor in self.supervisors.drain(..) {
            supervisor.abort();
        }
        if let Some(node) = self.node.take() {
            node.stop().await;
        }
        tracing::info!("gateway stopped");
    }
}

impl Drop for Gateway {
    /// A gateway dropped without running leaves no task behind.
    fn drop(&mut self) {
        for supervisor in &self.supervisors {
            supervisor.abort();
        }
    }
}
