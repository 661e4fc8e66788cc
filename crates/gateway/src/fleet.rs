//! Many elevator gateways in one process, for load tests of a portal (`canlift loadgen`, the
//! portal's benchmarks; docs/PORTAL.md §Load generator). Every one is the real gateway of this
//! crate in embedded mode — the same TLS, WebSocket, session, token store and reconnect code as
//! `canlift gateway` — sharing one simulated controller dictionary. Connections are spread over
//! loopback source addresses 127.0.0.1…127.0.0.N so that tens of thousands do not run out of
//! ephemeral ports.

use std::net::{IpAddr, Ipv4Addr};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use canopen::od::SharedDictionary;
use lift417::catalog::{Catalog, Device};
use tokio::sync::watch;
use tokio::task::JoinHandle;

use crate::{Gateway, GatewayError};

/// What a fleet is: where its gateways dial, as whom, how many and how fast.
#[derive(Debug, Clone)]
pub struct FleetOptions {
    /// The portal's gateway endpoint (`wss://HOST:PORT/ws`).
    pub portal: String,
    /// PEM CA certificate the gateways trust.
    pub ca: PathBuf,
    /// Domain token of the portal account the gateways belong to.
    pub domain: String,
    /// Gateways to run.
    pub gateways: usize,
    /// Number of the first gateway: serial numbers are LOAD-NNNNNN from here on.
    pub first: usize,
    /// Loopback source addresses to spread the connections over (127.0.0.1…127.0.0.N).
    pub sources: u8,
    /// Gateways started per second (0: all at once).
    pub rate: u32,
    /// Directory for the gateways' cloud tokens (reuse it and they reconnect as known lifts).
    pub state: PathBuf,
}

/// Why a fleet could not start.
#[derive(Debug, thiserror::Error)]
pub enum FleetError {
    /// No source address to connect from.
    #[error("sources: at least 1")]
    NoSources,
    /// The CA file.
    #[error(transparent)]
    Tls(#[from] tls::TlsError),
    /// The shared controller dictionary.
    #[error("the simulated controller's dictionary: {0}")]
    Dictionary(#[from] lift417::catalog::CatalogError),
    /// One gateway could not be made.
    #[error("gateway {number}: {error}")]
    Gateway {
        /// Its number.
        number: usize,
        /// Why.
        error: GatewayError,
    },
}

/// Not every gateway of a fleet came online in time.
#[derive(Debug, thiserror::Error)]
#[error("{online} of {of} gateways online after {after:?}")]
pub struct NotOnline {
    /// Online then.
    pub online: usize,
    /// The fleet's gateways.
    pub of: usize,
    /// How long was waited.
    pub after: Duration,
}

/// Fleet gateway `number`'s identity (NXg §5.2.1), of the account of `domain`.
pub fn identity(number: usize, domain: &str) -> nxg::gateway::Identity {
    nxg::gateway::Identity {
        sernum: format!("LOAD-{number:06}"),
        vendorid: 1050,
        productcode: 4097,
        domaintoken: domain.to_owned(),
        liftnum: format!("load {number}"),
        software: format!("canlift loadgen {}", env!("CARGO_PKG_VERSION")),
        ..Default::default()
    }
}

/// Running gateways.
pub struct Fleet {
    /// Each gateway's in-service status (`Gateway::online`).
    status: Vec<watch::Receiver<bool>>,
    stop: watch::Sender<bool>,
    tasks: Vec<JoinHandle<()>>,
    od: SharedDictionary,
    sessions: Sessions,
    launched: Instant,
}

/// Each gateway's TLS client configuration with a session cache of its own (as a device has):
/// handed from one fleet to the next, the gateways of the new fleet resume the TLS sessions of
/// the old one's (TLS 1.3 session tickets) instead of making full handshakes.
#[derive(Default)]
pub struct Sessions(Vec<Arc<rustls::ClientConfig>>);

impl Sessions {
    /// The configuration of gateway `i` of a fleet: the kept one, or `base` with a new cache.
    fn get(&mut self, i: usize, base: &rustls::ClientConfig) -> Arc<rustls::ClientConfig> {
        while self.0.len() <= i {
            let mut config = base.clone();
            config.resumption = rustls::client::Resumption::in_memory_sessions(4);
            self.0.push(Arc::new(config));
        }
        self.0[i].clone()
    }
}

impl Fleet {
    /// Make the gateways, then start them (at `options.rate` per second); returns once all
    /// are started. With the [`Sessions`] of an earlier fleet (see [`Fleet::stop`]) they
    /// resume its TLS sessions.
    pub async fn start(
        options: &FleetOptions,
        sessions: Option<Sessions>,
    ) -> Result<Fleet, FleetError> {
        if options.sources == 0 {
            return Err(FleetError::NoSources);
        }
        // One CA file read for all: tens of thousands of gateways trust the same portal.
        let base = tls::client_config(Some(&options.ca), None)?;
        let mut sessions = sessions.unwrap_or_default();
        let od = Catalog::builtin().dictionary(Device::Controller, 1, 8)?;
        // One description of the controller for all: each gateway's own copy was 1.6 MiB.
        let description = Arc::new(od.clone());
        let od: SharedDictionary = Arc::new(Mutex::new(od));
        let (stop, stopped) = watch::channel(false);
        // Every gateway is made before the first connects: a storm is of devices that exist,
        // and making one (its copy of the dictionary, its metadata) is no part of connecting.
        let mut gateways = Vec::with_capacity(options.gateways);
        for i in 0..options.gateways {
            let number = options.first + i;
            let mut config = crate::config::Config::for_portal(
                identity(number, &options.domain),
                &options.portal,
                &options.ca,
                "mem://loadgen",
                &options.state.join(format!("gw-{number:06}")),
            );
            let host = 1 + (i % usize::from(options.sources)) as u8;
            config.cloud.source_address = Some(IpAddr::V4(Ipv4Addr::new(127, 0, 0, host)));
            let gw = Gateway::embedded_with_tls(
                config,
                od.clone(),
                description.clone(),
                sessions.get(i, &base),
            )
            .map_err(|error| FleetError::Gateway { number, error })?;
            gateways.push(gw);
        }
        let status = gateways.iter().map(Gateway::online).collect();
        let launched = Instant::now();
        let mut tasks = Vec::with_capacity(options.gateways);
        for (i, gw) in gateways.into_iter().enumerate() {
            if options.rate > 0 {
                let due = launched + Duration::from_secs_f64(i as f64 / f64::from(options.rate));
                tokio::time::sleep_until(due.into()).await;
            }
            tasks.push(tokio::spawn(gw.run(stopped.clone())));
        }
        Ok(Fleet {
            status,
            stop,
            tasks,
            od,
            sessions,
            launched,
        })
    }

    /// When the first gateway began to connect.
    pub fn launched(&self) -> Instant {
        self.launched
    }

    /// How many gateways the fleet has.
    pub fn len(&self) -> usize {
        self.status.len()
    }

    /// Whether the fleet has no gateway.
    pub fn is_empty(&self) -> bool {
        self.status.is_empty()
    }

    /// Gateways in service now.
    pub fn online(&self) -> usize {
        self.status.iter().filter(|s| *s.borrow()).count()
    }

    /// Wait until all gateways are online; how long that took from `since`.
    pub async fn all_online(&self, since: Instant, limit: Duration) -> Result<Duration, NotOnline> {
        while self.online() < self.status.len() {
            if since.elapsed() > limit {
                return Err(NotOnline {
                    online: self.online(),
                    of: self.status.len(),
                    after: limit,
                });
            }
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
        Ok(since.elapsed())
    }

    /// Move the simulated lift one step: the trip counter, position, speed and load change, so
    /// every gateway that has them subscribed pushes them.
    pub fn change(&self, step: u32) {
        let mut od = self.od.lock().unwrap_or_else(PoisonError::into_inner);
        let changes: [(u16, u8, Vec<u8>); 4] = [
            (0x6520, 1, step.to_le_bytes().to_vec()),
            (0x6383, 1, (1000 + step % 20_000).to_le_bytes().to_vec()),
            (0x6390, 1, ((step % 1600) as i16).to_le_bytes().to_vec()),
            (0x6480, 1, ((step % 600) as u16).to_le_bytes().to_vec()),
        ];
        for (index, sub, bytes) in changes {
            if let Err(e) = od.set(index, sub, &bytes) {
                tracing::warn!(index, sub, error = %e, "loadgen could not change a value");
            }
        }
    }

    /// Stop every gateway (each closes its connection); their TLS sessions, for a next fleet.
    pub async fn stop(self) -> Sessions {
        self.stop.send_replace(true);
        for task in self.tasks {
            let _ = task.await;
        }
        self.sessions
    }
}
