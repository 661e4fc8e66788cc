//! `canlift bench portal`: the cloud portal under load (docs/BENCHMARKS.md). The portal runs as its own
//! process (`canlift cloud`), so its memory is its own; the gateways are `canlift loadgen`'s
//! (the real gateway code in embedded mode) in this process, and the operator-latency figure
//! uses a real gateway in bus-node mode in front of the simulated lift.
//!
//! Figures: idle TLS gateways held and the portal's memory per connection; a reconnect storm
//! (gateways with known tokens all at once, time until every one has CONNACK); notification
//! ingest into the database (stored and dropped per second); operator get latency portal →
//! gateway → SDO → simulator.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use lift417::sim::{SimConfig, Simulator};

use super::bench_gateway::{memory_kib, mib, percentile, Daemon};
use super::loadgen::{Fleet, LoadgenArgs};

/// Arguments of `canlift bench portal`.
#[derive(Debug, Clone, clap::Args)]
pub struct PortalBench {
    /// Idle gateways held at once.
    #[arg(long, default_value_t = 18_000)]
    gateways: usize,
    /// First-contact connections per second while they come (each gets a new token).
    #[arg(long, default_value_t = 2000)]
    rate: u32,
    /// Gateways (with known tokens) reconnecting all at once.
    #[arg(long, default_value_t = 10_000)]
    storm: usize,
    /// Gateways pushing values for the ingest figure.
    #[arg(long, default_value_t = 1000)]
    pushers: usize,
    /// How often the pushers' values change (ms).
    #[arg(long, default_value_t = 20)]
    change_ms: u64,
    /// Seconds of pushing.
    #[arg(long, default_value_t = 10)]
    seconds: u64,
    /// Operator gets for the latency figure.
    #[arg(long, default_value_t = 2000)]
    requests: usize,
    /// The portal's database (default: SQLite in a temporary directory); a postgres:// URL
    /// measures PostgreSQL.
    #[arg(long)]
    database: Option<String>,
    /// Loopback source addresses for the gateways (127.0.0.1…127.0.0.N).
    #[arg(long, default_value_t = 8)]
    sources: u8,
}

/// The portal process.
struct PortalProcess {
    daemon: Daemon,
    port: u16,
    ca: PathBuf,
    client: cloud::client::Client,
}

impl PortalProcess {
    async fn start(dir: &Path, database: &str) -> anyhow::Result<PortalProcess> {
        let port = std::net::TcpListener::bind("127.0.0.1:0")?
            .local_addr()?
            .port();
        let mut config = cloud::config::Config::default();
        config.server.listen = ([127, 0, 0, 1], port).into();
        config.state.dir = dir.join("portal");
        config.database.url = Some(database.to_owned());
        // Every change is pushed (no inhibit), so ingest is limited by the portal, not the
        // gateways' rate limiting.
        config.dashboard.inhibit_ms = 0;
        // The operator latency phase reads as fast as the portal answers, on one key.
        config.server.requests_per_key_s = 0;
        let path = dir.join("portal.toml");
        std::fs::write(&path, toml::to_string_pretty(&config)?)?;
        let daemon = Daemon::start(&std::env::current_exe()?, "cloud", &path)?;
        let ca = config.state.dir.join("dev-ca.pem");
        let deadline = Instant::now() + Duration::from_secs(30);
        while tokio::net::TcpStream::connect(("127.0.0.1", port))
            .await
            .is_err()
            || !ca.exists()
        {
            if Instant::now() > deadline {
                bail!("the portal did not start");
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let client =
            cloud::client::Client::new(&format!("https://localhost:{port}"), None, Some(&ca))?;
        Ok(PortalProcess {
            daemon,
            port,
            ca,
            client,
        })
    }

    /// One counter or gauge of `/metrics`.
    async fn metric(&self, name: &str) -> anyhow::Result<f64> {
        let (_, text) = self.client.call("GET", "/metrics", None).await?;
        let text = text.as_str().unwrap_or_default();
        text.lines()
            .find_map(|l| l.strip_prefix(name)?.trim().parse().ok())
            .with_context(|| format!("/metrics has no {name}"))
    }

    async fn online(&self) -> anyhow::Result<usize> {
        Ok(self.metric("canlift_gateways_online").await? as usize)
    }

    fn rss_kib(&self) -> u64 {
        memory_kib(self.daemon.pid).map_or(0, |m| m[0])
    }

    async fn stop(self) {
        self.daemon.stop(Duration::from_secs(10)).await;
    }
}

/// `n` gateways of the BENCH account, from `args.sources` source addresses, all at once.
fn fleet_args(args: &PortalBench, portal: &PortalProcess, dir: &Path, n: usize) -> LoadgenArgs {
    LoadgenArgs {
        portal: format!("wss://localhost:{}/ws", portal.port),
        ca: portal.ca.clone(),
        domain: "BENCH".into(),
        gateways: n,
        first: 1,
        sources: args.sources,
        rate: 0,
        change_ms: 0,
        state: dir.join("gateways"),
        until_online: true,
    }
}

/// Wait until the portal counts `n` gateways online.
async fn portal_online(portal: &PortalProcess, n: usize, limit: Duration) -> anyhow::Result<()> {
    let deadline = Instant::now() + limit;
    while portal.online().await? != n {
        if Instant::now() > deadline {
            bail!(
                "the portal counts {} online, not {n}",
                portal.online().await?
            );
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    Ok(())
}

async fn idle(args: &PortalBench, portal: &PortalProcess, dir: &Path) -> anyhow::Result<()> {
    tokio::time::sleep(Duration::from_secs(1)).await;
    let base = portal.rss_kib();
    let mut fleet_args = fleet_args(args, portal, dir, args.gateways);
    fleet_args.rate = args.rate;
    let begin = Instant::now();
    let fleet = Fleet::start(&fleet_args).await?;
    let took = fleet.all_online(begin, Duration::from_secs(600)).await?;
    portal_online(portal, args.gateways, Duration::from_secs(30)).await?;
    // Let the first contact's token writes and dashboard subscriptions settle.
    tokio::time::sleep(Duration::from_secs(5)).await;
    let held = portal.rss_kib();
    let per = (held.saturating_sub(base)) as f64 * 1024.0 / args.gateways as f64;
    println!(
        "idle gateways         {} online over TLS, first contact at {} /s took {:.1} s",
        args.gateways,
        args.rate,
        took.as_secs_f64()
    );
    println!(
        "portal memory         RSS {:.1} MiB idle → {:.1} MiB with {} gateways: {:.1} KiB per connection (goal ≤ 16 KiB)",
        mib(base),
        mib(held),
        args.gateways,
        per / 1024.0
    );
    let own = memory_kib(std::process::id()).map_or(0, |m| m[0]);
    println!(
        "loadgen memory        RSS {:.1} MiB for {} gateways (this process)",
        mib(own),
        args.gateways
    );
    fleet.stop().await;
    portal_online(portal, 0, Duration::from_secs(60)).await
}

async fn storm(args: &PortalBench, portal: &PortalProcess, dir: &Path) -> anyhow::Result<()> {
    let fleet_args = fleet_args(args, portal, dir, args.storm);
    let begin = Instant::now();
    let fleet = Fleet::start(&fleet_args).await?;
    let took = fleet.all_online(begin, Duration::from_secs(600)).await?;
    println!(
        "reconnect storm       {} gateways with known tokens at once: all CONNACK after {:.2} s ({:.0} /s)",
        args.storm,
        took.as_secs_f64(),
        args.storm as f64 / took.as_secs_f64()
    );
    fleet.stop().await;
    portal_online(portal, 0, Duration::from_secs(60)).await
}

async fn ingest(args: &PortalBench, portal: &PortalProcess, dir: &Path) -> anyhow::Result<()> {
    let fleet_args = fleet_args(args, portal, dir, args.pushers);
    let fleet = Fleet::start(&fleet_args).await?;
    fleet
        .all_online(Instant::now(), Duration::from_secs(120))
        .await?;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let stored0 = portal.metric("canlift_telemetry_stored_total").await?;
    let dropped0 = portal.metric("canlift_telemetry_dropped_total").await?;
    let begin = Instant::now();
    let mut tick = tokio::time::interval(Duration::from_millis(args.change_ms.max(1)));
    let mut step = 0u32;
    while begin.elapsed() < Duration::from_secs(args.seconds) {
        tick.tick().await;
        step = step.wrapping_add(1);
        fleet.change(step);
    }
    // What was sent in the window may still be on its way into the database.
    tokio::time::sleep(Duration::from_secs(2)).await;
    let seconds = begin.elapsed().as_secs_f64();
    let stored = portal.metric("canlift_telemetry_stored_total").await? - stored0;
    let dropped = portal.metric("canlift_telemetry_dropped_total").await? - dropped0;
    println!(
        "ingest                {} gateways pushing: {:.0} values/s stored, {:.0} /s dropped ({} changes every {} ms)",
        args.pushers,
        stored / seconds,
        dropped / seconds,
        4,
        args.change_ms
    );
    fleet.stop().await;
    portal_online(portal, 0, Duration::from_secs(60)).await
}

async fn latency(args: &PortalBench, portal: &PortalProcess, dir: &Path) -> anyhow::Result<()> {
    let store = cloud::store::Store::open(&database_url(args, dir)).await?;
    let key = store.add_account("operator", "OPS").await?;
    let bus = "mem://bench-portal";
    let sim = Simulator::start(bus, SimConfig::default()).await?;
    let identity = nxg::gateway::Identity {
        sernum: "BENCH-LIFT".into(),
        vendorid: 1050,
        productcode: 4096,
        domaintoken: "OPS".into(),
        ..Default::default()
    };
    let config = gateway::config::Config::for_portal(
        identity,
        &format!("wss://localhost:{}/ws", portal.port),
        &portal.ca,
        bus,
        &dir.join("lift-gateway"),
    );
    let gw = gateway::Gateway::bus_node(config).await?;
    let mut online = gw.online();
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let task = tokio::spawn(gw.run(stopped));
    tokio::time::timeout(Duration::from_secs(20), online.wait_for(|o| *o))
        .await
        .context("the lift's gateway did not come online")??;
    let client = cloud::client::Client::new(
        &format!("https://localhost:{}", portal.port),
        Some(&key),
        Some(&portal.ca),
    )?;
    let mut connection = client.connect().await?;
    for (form, query) in [("naked", "?form=naked"), ("full", "")] {
        let path = format!("/api/v1/lifts/1050-4096-BENCH-LIFT/objects/0x652001{query}");
        let mut times = Vec::with_capacity(args.requests);
        for _ in 0..args.requests {
            let sent = Instant::now();
            let (status, body) = connection.call("GET", &path, None).await?;
            if status != 200 {
                bail!("GET {path}: {status} {body}");
            }
            times.push(sent.elapsed());
        }
        times.sort();
        println!(
            "operator get ({form:<5})    p50 {:.0} µs   p99 {:.0} µs   (REST → portal → gateway → SDO → simulator, one connection)",
            percentile(&times, 50.0),
            percentile(&times, 99.0)
        );
    }
    stop.send_replace(true);
    let _ = task.await;
    sim.stop().await;
    Ok(())
}

fn database_url(args: &PortalBench, dir: &Path) -> String {
    args.database
        .clone()
        .unwrap_or_else(|| format!("sqlite://{}", dir.join("bench.db").display()))
}

/// `canlift bench portal`.
pub async fn run(args: PortalBench) -> anyhow::Result<()> {
    let dir = tempfile::Builder::new()
        .prefix("canlift-bench-portal-")
        .tempdir()?;
    let result = measure(&args, dir.path()).await;
    result
}

async fn measure(args: &PortalBench, dir: &Path) -> anyhow::Result<()> {
    let url = database_url(args, dir);
    let store = cloud::store::Store::open(&url).await?;
    if store.domain_exists("BENCH").await? {
        bail!("{url} already has the BENCH account: give a fresh database");
    }
    store.add_account("bench", "BENCH").await?;
    drop(store);
    let kind = if url.starts_with("postgres") {
        "PostgreSQL"
    } else {
        "SQLite"
    };
    println!(
        "portal on {kind}; gateways from 127.0.0.1…127.0.0.{}",
        args.sources
    );
    let portal = PortalProcess::start(dir, &url).await?;
    let outcome = async {
        idle(args, &portal, dir).await?;
        storm(args, &portal, dir).await?;
        ingest(args, &portal, dir).await?;
        latency(args, &portal, dir).await
    }
    .await;
    portal.stop().await;
    outcome
}
