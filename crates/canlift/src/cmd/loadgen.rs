//! `canlift loadgen`: many elevator gateways against one portal, for the portal's benchmarks
//! (docs/PORTAL.md §Load generator). Every one is the real gateway of `crates/gateway` in embedded mode — the same TLS,
//! WebSocket, session, token store and reconnect code as `canlift gateway` — sharing one
//! simulated controller dictionary. Connections are spread over loopback source addresses
//! 127.0.0.1…127.0.0.N so that tens of thousands do not run out of ephemeral ports.

use std::net::{IpAddr, Ipv4Addr};
use std::path::PathBuf;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use canopen::driver::SharedDictionary;
use gateway::Gateway;
use lift417::catalog::{Catalog, Device};
use tokio::sync::watch;
use tokio::task::JoinHandle;

/// Arguments of `canlift loadgen`.
#[derive(Debug, Clone, clap::Args)]
pub struct LoadgenArgs {
    /// The portal's gateway endpoint.
    #[arg(long, default_value = "wss://localhost:8443/ws")]
    pub portal: String,
    /// PEM CA certificate the gateways trust (the portal's dev-ca.pem).
    #[arg(long)]
    pub ca: PathBuf,
    /// Domain token of the portal account the gateways belong to.
    #[arg(long)]
    pub domain: String,
    /// Gateways to run.
    #[arg(long, default_value_t = 1000)]
    pub gateways: usize,
    /// Number of the first gateway: serial numbers are LOAD-NNNNNN from here on.
    #[arg(long, default_value_t = 1)]
    pub first: usize,
    /// Loopback source addresses to spread the connections over (127.0.0.1…127.0.0.N).
    #[arg(long, default_value_t = 8)]
    pub sources: u8,
    /// Gateways started per second (0: all at once).
    #[arg(long, default_value_t = 0)]
    pub rate: u32,
    /// Change the simulated lift's values this often (ms) so that every gateway pushes what
    /// the portal subscribed; 0: the gateways stay idle.
    #[arg(long, default_value_t = 0)]
    pub change_ms: u64,
    /// Directory for the gateways' cloud tokens (reuse it and they reconnect as known lifts).
    #[arg(long, default_value = "loadgen-state")]
    pub state: PathBuf,
    /// Exit once all are online, after printing how long it took.
    #[arg(long)]
    pub until_online: bool,
}

/// Load-generator gateway `number`'s identity (NXg §5.2.1), of the account of `domain`.
fn identity(number: usize, domain: &str) -> nxg::gateway::Identity {
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

/// The portal's lift id of load-generator gateway `number`.
#[cfg(feature = "portal")]
pub(crate) fn lift_id(number: usize) -> String {
    cloud::store::lift_id(&identity(number, "").connect(None).identity)
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

/// The shared controller dictionary the gateways serve.
fn dictionary() -> anyhow::Result<SharedDictionary> {
    let od = Catalog::builtin().dictionary(Device::Controller, 1, 8)?;
    Ok(Arc::new(Mutex::new(od)))
}

impl Fleet {
    /// Make the gateways, then start them (at `rate` per second); returns once all are
    /// started. With the
    /// [`Sessions`] of an earlier fleet (see [`Fleet::stop`]) they resume its TLS sessions.
    pub async fn start(args: &LoadgenArgs, sessions: Option<Sessions>) -> anyhow::Result<Fleet> {
        if args.sources == 0 {
            bail!("--sources: at least 1");
        }
        // One CA file read for all: tens of thousands of gateways trust the same portal.
        let base = tls::client_config(Some(&args.ca), None)?;
        let mut sessions = sessions.unwrap_or(Sessions(Vec::new()));
        let od = dictionary()?;
        // One description of the controller for all: each gateway's own copy was 1.6 MiB.
        let description = Arc::new(od.lock().unwrap_or_else(PoisonError::into_inner).clone());
        let (stop, stopped) = watch::channel(false);
        // Every gateway is made before the first connects: a storm is of devices that exist,
        // and making one (its copy of the dictionary, its metadata) is no part of connecting.
        let mut gateways = Vec::with_capacity(args.gateways);
        for i in 0..args.gateways {
            let number = args.first + i;
            let identity = identity(number, &args.domain);
            let mut config = gateway::config::Config::for_portal(
                identity,
                &args.portal,
                &args.ca,
                "mem://loadgen",
                &args.state.join(format!("gw-{number:06}")),
            );
            let host = 1 + (i % usize::from(args.sources)) as u8;
            config.cloud.source_address = Some(IpAddr::V4(Ipv4Addr::new(127, 0, 0, host)));
            let gw = Gateway::embedded_with_tls(
                config,
                od.clone(),
                description.clone(),
                sessions.get(i, &base),
            )
            .with_context(|| format!("gateway {number}"))?;
            gateways.push(gw);
        }
        let status = gateways.iter().map(Gateway::online).collect();
        let launched = Instant::now();
        let mut tasks = Vec::with_capacity(args.gateways);
        for (i, gw) in gateways.into_iter().enumerate() {
            if args.rate > 0 {
                let due = launched + Duration::from_secs_f64(i as f64 / f64::from(args.rate));
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

    /// Gateways in service now.
    pub fn online(&self) -> usize {
        self.status.iter().filter(|s| *s.borrow()).count()
    }

    /// Wait until all gateways are online; how long that took from `since`.
    pub async fn all_online(&self, since: Instant, limit: Duration) -> anyhow::Result<Duration> {
        while self.online() < self.status.len() {
            if since.elapsed() > limit {
                bail!(
                    "{} of {} gateways online after {limit:?}",
                    self.online(),
                    self.status.len()
                );
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

/// `canlift loadgen`.
pub async fn run(args: LoadgenArgs) -> anyhow::Result<()> {
    let begin = Instant::now();
    let fleet = Fleet::start(&args, None).await?;
    println!(
        "{} gateways made in {:.1} s and started in {:.1} s; waiting for CONNACK",
        args.gateways,
        fleet.launched().duration_since(begin).as_secs_f64(),
        fleet.launched().elapsed().as_secs_f64()
    );
    let mut report = tokio::time::interval(Duration::from_secs(1));
    let mut change = tokio::time::interval(Duration::from_millis(args.change_ms.max(1)));
    let mut step = 0u32;
    let shutdown = crate::logging::shutdown_signal();
    tokio::pin!(shutdown);
    {
        let all_online = fleet.all_online(fleet.launched(), Duration::from_secs(24 * 3600));
        tokio::pin!(all_online);
        let mut all = false;
        loop {
            tokio::select! {
                took = &mut all_online, if !all => {
                    all = true;
                    match took {
                        Ok(t) => println!("all {} online after {:.2} s", args.gateways, t.as_secs_f64()),
                        Err(e) => println!("{e}"),
                    }
                    if args.until_online {
                        break;
                    }
                }
                _ = report.tick(), if !all => {
                    println!("{} online after {:.0} s", fleet.online(), fleet.launched().elapsed().as_secs_f64());
                }
                _ = change.tick(), if args.change_ms > 0 => {
                    step = step.wrapping_add(1);
                    fleet.change(step);
                }
                _ = &mut shutdown => break,
            }
        }
    }
    fleet.stop().await;
    Ok(())
}
