//! `canlift-bench portal`: the cloud portal under load (docs/BENCHMARKS.md). The portal runs as its own
//! process (`canlift cloud`), so its memory is its own; the gateways are `canlift loadgen`'s
//! (the real gateway code in embedded mode) in this process, and the operator-latency figure's
//! gateway is one in a process of its own.
//!
//! Figures: idle TLS gateways held and the portal's memory per connection; a reconnect storm
//! (gateways with known tokens all at once, time until every one has CONNACK); notification
//! ingest into the database (stored and dropped per second); operator get latency through the
//! portal against the same gateway read directly and through a bare relay process.

mod curves;

use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};

use crate::process::{cpu_time, listening, per_one, schedstat, used_since};
use crate::process::{lone_gateway, memory_kib, mib, percentile, Daemon};
use gateway::fleet::{Fleet, FleetOptions, Sessions};

/// Arguments of `canlift-bench portal`.
#[derive(Debug, Clone, clap::Args)]
pub struct PortalBench {
    /// Idle gateways held at once (and the largest number of the curves).
    #[arg(long, default_value_t = 18_000)]
    pub(super) gateways: usize,
    /// First-contact connections per second while they come (each gets a new token).
    #[arg(long, default_value_t = 2000)]
    pub(super) rate: u32,
    /// Gateways (with known tokens) reconnecting all at once.
    #[arg(long, default_value_t = 10_000)]
    pub(super) storm: usize,
    /// Gateways pushing values for the ingest figure.
    #[arg(long, default_value_t = 1000)]
    pub(super) pushers: usize,
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
    /// The phases to run, in this order.
    #[arg(
        long,
        value_enum,
        value_delimiter = ',',
        default_value = "idle,storm,ingest,latency"
    )]
    phases: Vec<Phase>,
    /// Where the `curves` phase writes its CSV and SVG files.
    #[arg(long, default_value = "docs/bench")]
    curves: PathBuf,
    /// The CPUs the portal runs on (`taskset -c` list, e.g. `0`); with the benchmark itself
    /// started on others (`taskset -c 1 canlift-bench portal --portal-cpus 0`) the load
    /// generator takes none of the portal's cores, and its figures are the portal's alone.
    #[arg(long)]
    portal_cpus: Option<String>,
}

/// A phase of `bench portal`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
enum Phase {
    /// Idle gateways held, memory per connection.
    Idle,
    /// Reconnect storms: new TLS sessions, resumed, resumed after a portal restart.
    Storm,
    /// Values pushed and stored.
    Ingest,
    /// Operator reads through the portal.
    Latency,
    /// Growth curves: memory vs gateways, storm time vs gateways, ingest vs pushers (CSV and
    /// SVG into `--curves`).
    Curves,
}

/// A portal process (`canlift cloud`) of a benchmark.
pub(crate) struct PortalProcess {
    pub(crate) daemon: Daemon,
    pub(crate) port: u16,
    pub(crate) ca: PathBuf,
    /// The CPUs it runs on (`--portal-cpus`), for a restart to keep.
    cpus: Option<String>,
    /// Its `/metrics` listener (`[server] metrics_listen`).
    metrics: std::net::SocketAddr,
}

/// Counter or gauge `name` of a `/metrics` answer.
pub(crate) fn metric(scraped: &cloud::client::Scraped, name: &str) -> anyhow::Result<f64> {
    scraped
        .sum(name)
        .with_context(|| format!("/metrics has no {name}"))
}

/// The benchmarks' portal configuration: on a free loopback port, state in `dir/portal`,
/// every change pushed (no inhibit: ingest is limited by the portal, not by the gateways' rate
/// limiting) and no request limit per key (the latency figures read as fast as it answers).
pub(crate) fn bench_config(dir: &Path, database: &str) -> anyhow::Result<cloud::config::Config> {
    let port = testkit::free_port();
    let mut config = cloud::config::Config::default();
    config.server.listen = ([127, 0, 0, 1], port).into();
    config.state.dir = dir.join("portal");
    config.database.url = Some(database.to_owned());
    config.dashboard.inhibit_ms = 0;
    config.server.requests_per_key_s = 0;
    // The benchmark reads /metrics as a scraper would, on a listener of its own: on the
    // portal's port it would wait behind a storm's gateways (and count among its handshakes).
    config.server.metrics_listen = Some(([127, 0, 0, 1], testkit::free_port()).into());
    Ok(config)
}

impl PortalProcess {
    async fn start(
        dir: &Path,
        database: &str,
        cpus: Option<String>,
    ) -> anyhow::Result<PortalProcess> {
        let config = bench_config(dir, database)?;
        let ca = config.state.dir.join("dev-ca.pem");
        PortalProcess::start_with(dir, &config, ca, cpus).await
    }

    /// Start `canlift cloud` with `config` (written into `dir`), on `cpus` when given; `ca` is
    /// what its certificate is of. Returns once it listens.
    pub(crate) async fn start_with(
        dir: &Path,
        config: &cloud::config::Config,
        ca: PathBuf,
        cpus: Option<String>,
    ) -> anyhow::Result<PortalProcess> {
        let port = config.server.listen.port();
        let path = dir.join("portal.toml");
        std::fs::create_dir_all(dir)?;
        std::fs::write(&path, toml::to_string_pretty(config)?)?;
        let daemon = Daemon::start(&crate::canlift()?, "cloud", &path, cpus.as_deref())?;
        // The portal writes its development CA before it listens.
        listening(port, "the portal", Duration::from_secs(30)).await?;
        if !ca.exists() {
            bail!("the portal listens but {} is missing", ca.display());
        }
        let metrics = config
            .server
            .metrics_listen
            .context("the benchmarks read /metrics on [server] metrics_listen")?;
        Ok(PortalProcess {
            daemon,
            port,
            ca,
            cpus,
            metrics,
        })
    }

    /// `/metrics` (an error after 10 s: a process at its file limit accepts no connection).
    pub(crate) async fn scrape(&self) -> anyhow::Result<cloud::client::Scraped> {
        let metrics = self.metrics;
        tokio::time::timeout(Duration::from_secs(10), cloud::client::scrape(metrics))
            .await
            .with_context(|| format!("/metrics of {metrics}: no answer in 10 s"))?
            .with_context(|| format!("/metrics of {metrics}"))
    }

    /// One counter or gauge of `/metrics`.
    pub(crate) async fn metric(&self, name: &str) -> anyhow::Result<f64> {
        metric(&self.scrape().await?, name)
    }

    async fn online(&self) -> anyhow::Result<usize> {
        Ok(self.metric("canlift_gateways_online").await? as usize)
    }

    pub(crate) fn rss_kib(&self) -> u64 {
        memory_kib(self.daemon.pid).map_or(0, |m| m[0])
    }

    pub(crate) async fn stop(mut self) {
        self.daemon.stop(Duration::from_secs(10)).await;
    }

    /// Replace the portal by a new process on the same state directory and database (stopped
    /// first: one portal at a time holds a SQLite portal's state; the new one on a port of its
    /// own).
    async fn restart(&mut self, dir: &Path, database: &str) -> anyhow::Result<()> {
        self.daemon.stop(Duration::from_secs(10)).await;
        *self = PortalProcess::start(dir, database, self.cpus.take()).await?;
        Ok(())
    }
}

/// The portal's lift id of fleet gateway `number`.
pub(crate) fn lift_id(number: usize) -> String {
    cloud_types::lifts::lift_id(&gateway::fleet::identity(number, "").connect(None).identity)
}

/// `n` gateways of the BENCH account, from `args.sources` source addresses, all at once.
pub(super) fn fleet_args(
    args: &PortalBench,
    portal: &PortalProcess,
    dir: &Path,
    n: usize,
) -> FleetOptions {
    FleetOptions {
        portal: format!("wss://localhost:{}/ws", portal.port),
        ca: portal.ca.clone(),
        domain: "BENCH".into(),
        gateways: n,
        first: 1,
        sources: args.sources,
        rate: 0,
        state: dir.join("gateways"),
    }
}

/// Wait until the portal counts `n` gateways online.
pub(super) async fn portal_online(
    portal: &PortalProcess,
    n: usize,
    limit: Duration,
) -> anyhow::Result<()> {
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
    let fleet = Fleet::start(&fleet_args, None).await?;
    let took = fleet
        .all_online(fleet.launched(), Duration::from_secs(600))
        .await?;
    portal_online(portal, args.gateways, Duration::from_secs(30)).await?;
    // Let the first contact's token writes and dashboard subscriptions settle, and the portal
    // give back what the burst left free (it looks every 5 s: docs/PORTAL.md §Memory).
    tokio::time::sleep(Duration::from_secs(5)).await;
    trimmed_since(portal, 0.0).await?;
    let trimmed = portal.metric("canlift_memory_trimmed_bytes_total").await?;
    let held = portal.rss_kib();
    let per_connection = |rss_kib: f64| (rss_kib - base as f64).max(0.0) / args.gateways as f64;
    let per = per_connection(held as f64);
    println!(
        "idle gateways         {} online over TLS, first contact at {} /s took {:.1} s",
        args.gateways,
        args.rate,
        took.as_secs_f64()
    );
    println!(
        "portal memory         RSS {:.1} MiB idle → {:.1} MiB with {} gateways: {:.1} KiB per connection (goal ≤ 10 KiB)",
        mib(base),
        mib(held),
        args.gateways,
        per
    );
    println!(
        "memory given back     {:.1} MiB after the burst (canlift_memory_trimmed_bytes_total; \
         {:.1} KiB per connection before)",
        trimmed / 1_048_576.0,
        per_connection(held as f64 + trimmed / 1024.0)
    );
    let own = memory_kib(std::process::id()).map_or(0, |m| m[0]);
    println!(
        "loadgen memory        RSS {:.1} MiB for {} gateways (this process)",
        mib(own),
        args.gateways
    );
    fleet.stop().await;
    portal_online(portal, 0, Duration::from_secs(60)).await?;
    let trims = portal.metric("canlift_memory_trims_total").await?;
    trimmed_since(portal, trims).await?;
    println!(
        "portal memory         RSS {:.1} MiB once they are all gone ({:.1} MiB given back in all)",
        mib(portal.rss_kib()),
        portal.metric("canlift_memory_trimmed_bytes_total").await? / 1_048_576.0
    );
    Ok(())
}

/// Wait (at most 15 s) until the portal has given memory back after a burst: more trims than
/// `trims` (docs/PORTAL.md §Memory).
async fn trimmed_since(portal: &PortalProcess, trims: f64) -> anyhow::Result<()> {
    let deadline = Instant::now() + Duration::from_secs(15);
    while portal.metric("canlift_memory_trims_total").await? <= trims && Instant::now() < deadline {
        tokio::time::sleep(Duration::from_millis(250)).await;
    }
    Ok(())
}

/// CPU time the portal process and this one (the load generator) spend from now on.
struct CpuMeter {
    pid: u32,
    start: (Duration, Duration),
}

impl CpuMeter {
    fn now(pid: u32) -> (Duration, Duration) {
        let of = |pid| cpu_time(pid).unwrap_or_default();
        (of(pid), of(std::process::id()))
    }

    fn start(portal: &PortalProcess) -> CpuMeter {
        CpuMeter {
            pid: portal.daemon.pid,
            start: CpuMeter::now(portal.daemon.pid),
        }
    }

    /// (portal, load generator) since the start.
    fn read(&self) -> (Duration, Duration) {
        let (portal, own) = CpuMeter::now(self.pid);
        (
            portal.saturating_sub(self.start.0),
            own.saturating_sub(self.start.1),
        )
    }
}

/// The portal's TLS handshakes so far: (full, resumed).
async fn handshakes(portal: &PortalProcess) -> anyhow::Result<(f64, f64)> {
    Ok((
        portal.metric("canlift_tls_handshakes_full_total").await?,
        portal
            .metric("canlift_tls_handshakes_resumed_total")
            .await?,
    ))
}

/// `args.storm` gateways with known tokens at once (with `sessions`: resuming their TLS
/// sessions); time until all have CONNACK (returned with the sessions), the handshakes the
/// portal made, its CPU time.
pub(super) async fn storm_once(
    args: &PortalBench,
    portal: &PortalProcess,
    dir: &Path,
    sessions: Option<Sessions>,
    what: &str,
) -> anyhow::Result<(Sessions, Duration)> {
    let fleet_args = fleet_args(args, portal, dir, args.storm);
    let (full0, resumed0) = handshakes(portal).await?;
    // A mark for whoever profiles the portal alongside (docs/BENCHMARKS.md §Reconnect storm):
    // the storm begins now, and ends at its figures' line.
    eprintln!("reconnect storm begins: {what}");
    let fleet = Fleet::start(&fleet_args, sessions).await?;
    let meter = CpuMeter::start(portal);
    let took = fleet
        .all_online(fleet.launched(), Duration::from_secs(600))
        .await?;
    let (cpu, own) = meter.read();
    let (full, resumed) = handshakes(portal).await?;
    println!(
        "reconnect storm       {} gateways with known tokens at once, {what}: all CONNACK after {:.2} s ({:.0} /s); handshakes {:.0} full, {:.0} resumed; CPU per connection: portal {:.0} µs, load generator {:.0} µs",
        args.storm,
        took.as_secs_f64(),
        args.storm as f64 / took.as_secs_f64(),
        full - full0,
        resumed - resumed0,
        cpu.as_secs_f64() * 1e6 / args.storm as f64,
        own.as_secs_f64() * 1e6 / args.storm as f64,
    );
    let sessions = fleet.stop().await;
    portal_online(portal, 0, Duration::from_secs(60)).await?;
    Ok((sessions, took))
}

/// The reconnect storm three times: new gateway processes (full handshakes), gateways that
/// keep their TLS sessions (resumed), and the same after the portal restarted (its ticket keys
/// are in its state directory).
async fn storm(
    args: &PortalBench,
    portal: &mut PortalProcess,
    dir: &Path,
    database: &str,
) -> anyhow::Result<()> {
    if !args.phases.contains(&Phase::Idle) {
        // The storm is of known gateways: let them make first contact (not timed).
        let fleet = Fleet::start(&fleet_args(args, portal, dir, args.storm), None).await?;
        fleet
            .all_online(Instant::now(), Duration::from_secs(600))
            .await?;
        fleet.stop().await;
        portal_online(portal, 0, Duration::from_secs(60)).await?;
    }
    let (sessions, _) = storm_once(args, portal, dir, None, "new TLS sessions").await?;
    let (sessions, _) = storm_once(args, portal, dir, Some(sessions), "resuming").await?;
    portal.restart(dir, database).await?;
    storm_once(
        args,
        portal,
        dir,
        Some(sessions),
        "resuming after a portal restart",
    )
    .await?;
    gave_up(args, portal).await
}

/// `args.storm` clients that give up behind their ClientHello, as gateways whose timeout ran
/// out while their connections waited in a storm: each sends the hello and closes the
/// connection in one segment (corked, so the portal cannot read the one without the other).
/// What each costs the portal, and how many it dropped unanswered (docs/PORTAL.md §TLS).
async fn gave_up(args: &PortalBench, portal: &PortalProcess) -> anyhow::Result<()> {
    use tokio::io::AsyncWriteExt;
    let config = tls::client_config(Some(&portal.ca), None)?;
    let mut hello = Vec::new();
    rustls::ClientConnection::new(
        config,
        rustls::pki_types::ServerName::try_from("localhost")?,
    )?
    .write_tls(&mut hello)?;
    let abandoned = || portal.metric("canlift_tls_handshakes_abandoned_total");
    let before = abandoned().await?;
    let meter = CpuMeter::start(portal);
    for _ in 0..args.storm {
        let mut socket = tokio::net::TcpStream::connect(("127.0.0.1", portal.port)).await?;
        socket2::SockRef::from(&socket).set_tcp_cork(true)?;
        socket.write_all(&hello).await?;
        socket.shutdown().await?;
    }
    // Until the portal has looked at all of them: its CPU no longer grows.
    let mut last = meter.read().0;
    loop {
        tokio::time::sleep(Duration::from_millis(500)).await;
        let now = meter.read().0;
        if now.saturating_sub(last) < Duration::from_millis(5) {
            break;
        }
        last = now;
    }
    let (cpu, _) = meter.read();
    println!(
        "clients that gave up  {} sent a ClientHello and closed behind it: {:.0} dropped unanswered; CPU per connection: portal {:.0} µs",
        args.storm,
        abandoned().await? - before,
        cpu.as_secs_f64() * 1e6 / args.storm as f64,
    );
    Ok(())
}

/// `args.pushers` gateways pushing for `args.seconds`: values stored per second (returned),
/// dropped, the portal's CPU per value.
pub(super) async fn ingest(
    args: &PortalBench,
    portal: &PortalProcess,
    dir: &Path,
) -> anyhow::Result<f64> {
    let fleet_args = fleet_args(args, portal, dir, args.pushers);
    let fleet = Fleet::start(&fleet_args, None).await?;
    fleet
        .all_online(Instant::now(), Duration::from_secs(120))
        .await?;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let stored0 = portal.metric("canlift_telemetry_stored_total").await?;
    let dropped0 = portal.metric("canlift_telemetry_dropped_total").await?;
    let waits0 = portal.metric("canlift_telemetry_waits_total").await?;
    let meter = CpuMeter::start(portal);
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
    let waits = portal.metric("canlift_telemetry_waits_total").await? - waits0;
    let (cpu, own) = meter.read();
    println!(
        "ingest                {} gateways pushing: {:.0} values/s stored, {:.0} /s dropped, {:.0} /s waited for room ({} changes every {} ms); portal CPU {:.1} µs per value received ({:.0} % of a core), load generator {:.0} % of a core",
        args.pushers,
        stored / seconds,
        dropped / seconds,
        waits / seconds,
        4,
        args.change_ms,
        cpu.as_secs_f64() * 1e6 / (stored + dropped).max(1.0),
        cpu.as_secs_f64() * 100.0 / seconds,
        own.as_secs_f64() * 100.0 / seconds,
    );
    fleet.stop().await;
    portal_online(portal, 0, Duration::from_secs(60)).await?;
    Ok(stored / seconds)
}

/// Load-generator number of the latency phase's gateway (clear of the fleets' 1, 2, …).
const LATENCY_GATEWAY: usize = 900_000;

/// Rounds the latency phase interleaves its three ways in, so that a slow patch of the VM
/// falls on each of them alike.
const ROUNDS: usize = 5;

/// One way to the latency phase's gateway.
enum Way {
    /// A stand-in portal's end of the gateway's WebSocket (directly, or through `bench relay`).
    Door(Box<crate::gateway::Ws>),
    /// The portal's REST API, one keep-alive HTTPS connection.
    Portal(cloud::client::Connection),
}

impl Way {
    /// `n` gets of 0x652001 in `form` one after another; their times.
    async fn gets(&mut self, form: &str, n: usize) -> anyhow::Result<Vec<Duration>> {
        let connection = match self {
            Way::Door(ws) => return crate::gateway::sequential_gets(ws, form, n).await,
            Way::Portal(connection) => connection,
        };
        let path = path_of(form);
        let mut times = Vec::with_capacity(n);
        for _ in 0..n {
            times.push(timed_get(connection, &path).await?);
        }
        Ok(times)
    }
}

/// One GET of `path` that must answer 200; how long it took.
async fn timed_get(
    connection: &mut cloud::client::Connection,
    path: &str,
) -> anyhow::Result<Duration> {
    let sent = Instant::now();
    let (status, body) = connection.call("GET", path, None).await?;
    if status != 200 {
        bail!("GET {path}: {status} {body}");
    }
    Ok(sent.elapsed())
}

/// The REST path of the latency phase's get in `form`.
fn path_of(form: &str) -> String {
    let query = if form == "naked" { "?form=naked" } else { "" };
    format!(
        "/api/v1/lifts/{}/objects/0x652001{query}",
        lift_id(LATENCY_GATEWAY)
    )
}

/// Operators reading one lift at once through the portal, each on a connection of its own (a
/// lift page asking for its objects): reads per second, and the CPU and wake-ups per read of the
/// portal and of the gateway (`pids`).
async fn together(
    client: &cloud::client::Client,
    path: &str,
    reads: usize,
    pids: [u32; 2],
) -> anyhow::Result<()> {
    const OPERATORS: usize = 32;
    let mut connections = Vec::with_capacity(OPERATORS);
    for _ in 0..OPERATORS {
        connections.push(client.connect().await?);
    }
    let each = reads.div_ceil(OPERATORS);
    let before = pids.map(schedstat);
    let started = Instant::now();
    futures_util::future::try_join_all(connections.iter_mut().map(|connection| async move {
        for _ in 0..each {
            timed_get(connection, path).await?;
        }
        anyhow::Ok(())
    }))
    .await?;
    let elapsed = started.elapsed();
    let total = (each * OPERATORS) as f64;
    let [portal, gateway] = [0, 1].map(|k| per_one(used_since(pids[k], before[k]), total));
    println!(
        "{OPERATORS} operators at once (naked)  {:.0} reads/s; per read: the portal {portal}, the gateway {gateway}",
        total / elapsed.as_secs_f64()
    );
    Ok(())
}

/// The web UI's page of the lift, signed in with `key`, 1,000 times one after another (the page
/// reads each object it shows from the gateway, all at once): its time, and the CPU and
/// wake-ups per page of the portal and of the gateway (`pids`).
async fn lift_pages(
    client: &cloud::client::Client,
    key: &str,
    pids: [u32; 2],
) -> anyhow::Result<()> {
    const PAGES: usize = 1000;
    let signed_in = client
        .exchange("POST", "/login", cloud::client::Body::Form(&[("key", key)]))
        .await?;
    let cookie = signed_in
        .set_cookie
        .with_context(|| format!("signing in: {}", signed_in.status))?;
    let mut connection = client.clone().with_cookie(&cookie).connect().await?;
    let path = format!("/lifts/{}", lift_id(LATENCY_GATEWAY));
    let before = pids.map(schedstat);
    let mut times = Vec::with_capacity(PAGES);
    for _ in 0..PAGES {
        times.push(timed_get(&mut connection, &path).await?);
    }
    times.sort();
    let [portal, gateway] = [0, 1].map(|k| per_one(used_since(pids[k], before[k]), PAGES as f64));
    println!(
        "the lift's web page  p50 {:.0} µs, p99 {:.0} µs; per page: the portal {portal}, the gateway {gateway}",
        percentile(&times, 50.0),
        percentile(&times, 99.0)
    );
    Ok(())
}

/// Operator gets of one gateway three ways, every party a process of its own as in the field:
/// at the gateway's own door (a stand-in portal in this process), through a process that only
/// copies bytes (`bench relay`: the least any process in the path costs on this machine), and
/// through the portal (REST over HTTPS). The three gateways are the same embedded gateway
/// (`canlift loadgen`, local dictionary), each in its own process.
async fn latency(args: &PortalBench, portal: &PortalProcess, dir: &Path) -> anyhow::Result<()> {
    let exe = crate::canlift()?;
    let store = cloud_store::Store::open(&database_url(args, dir)).await?;
    let key = store.add_account("operator", "OPS").await?;
    let pki = cloud::devpki::ensure(&dir.join("stand-in"))?;
    let harness = crate::gateway::Portal::start(&pki).await?;
    let lone = |url: &str, ca: &Path, state: &str| {
        lone_gateway(&exe, url, ca, "OPS", LATENCY_GATEWAY, &dir.join(state))
    };
    let mut daemons = vec![lone(&harness.url()?, &pki.ca, "latency-direct")?];
    let direct = harness.accept().await?;
    let relay_port = testkit::free_port();
    let (listen, to) = (
        format!("127.0.0.1:{relay_port}"),
        harness.addr()?.to_string(),
    );
    // The relay is this benchmark's own hidden subcommand, not canlift's.
    let bench = std::env::current_exe().context("locating canlift-bench")?;
    let relay = Daemon::spawn(
        &bench,
        &[
            "relay".as_ref(),
            "--listen".as_ref(),
            listen.as_ref(),
            "--to".as_ref(),
            to.as_ref(),
        ],
        Stdio::inherit(),
    )?;
    listening(relay_port, "the relay", Duration::from_secs(20)).await?;
    let relayed_url = format!("wss://localhost:{relay_port}/ws");
    daemons.push(lone(&relayed_url, &pki.ca, "latency-relayed")?);
    let relayed = harness.accept().await?;
    let portal_url = format!("wss://localhost:{}/ws", portal.port);
    let held = lone(&portal_url, &portal.ca, "latency-portal")?;
    let client = cloud::client::Client::new(
        &format!("https://localhost:{}", portal.port),
        Some(&key),
        Some(&portal.ca),
    )?;
    let mut through_portal = Way::Portal(client.connect().await?);
    let deadline = Instant::now() + Duration::from_secs(20);
    while let Err(e) = through_portal.gets("naked", 1).await {
        if Instant::now() > deadline {
            return Err(e.context("the lift's gateway did not come online"));
        }
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // Each way with the process it adds (none: directly), whose CPU per read is measured
    // beside this process's own (the stand-in's or the HTTPS client's).
    let mut ways = [
        (Way::Door(Box::new(direct)), None),
        (Way::Door(Box::new(relayed)), Some(relay.pid)),
        (through_portal, Some(portal.daemon.pid)),
    ];
    let forms = ["naked", "full"];
    let mut times = vec![vec![Vec::new(); forms.len()]; ways.len()];
    let mut used = vec![[(Duration::ZERO, 0); 2]; ways.len()];
    for (way, _) in &mut ways {
        way.gets("naked", 200).await?;
    }
    let per_round = args.requests.div_ceil(ROUNDS);
    for _ in 0..ROUNDS {
        for (f, form) in forms.iter().enumerate() {
            for (w, (way, pid)) in ways.iter_mut().enumerate() {
                let pids = [*pid, Some(std::process::id())];
                let before = pids.map(|p| p.and_then(schedstat));
                times[w][f].extend(way.gets(form, per_round).await?);
                for (k, (p, before)) in pids.into_iter().zip(before).enumerate() {
                    if let Some((cpu, slices)) = p.and_then(|p| used_since(p, before)) {
                        used[w][k].0 += cpu;
                        used[w][k].1 += slices;
                    }
                }
            }
        }
    }
    for (f, form) in forms.iter().enumerate() {
        let mut stats = |w: usize| {
            times[w][f].sort();
            (
                percentile(&times[w][f], 50.0),
                percentile(&times[w][f], 99.0),
            )
        };
        let [(d50, d99), (r50, r99), (p50, p99)] = [stats(0), stats(1), stats(2)];
        println!(
            "operator get ({form:<5})  p50 / p99: directly {d50:.0} / {d99:.0} µs, through a relay {r50:.0} / {r99:.0} µs, through the portal {p50:.0} / {p99:.0} µs"
        );
        println!(
            "  the portal adds {:.0} µs at p50; a process that only relays adds {:.0} µs; the portal's own share {:.0} µs",
            p50 - d50,
            r50 - d50,
            p50 - r50
        );
    }
    let reads = (per_round * ROUNDS * forms.len()) as f64;
    let per_read = |used| per_one(Some(used), reads);
    println!(
        "  per read: the relay {}, the portal {} ({reads} reads each way, {ROUNDS} rounds interleaved)",
        per_read(used[1][0]),
        per_read(used[2][0]),
    );
    println!(
        "  this process per read: at the door {}, through the relay {}, through the portal (the HTTPS client) {}",
        per_read(used[0][1]),
        per_read(used[1][1]),
        per_read(used[2][1]),
    );
    let pids = [portal.daemon.pid, held.pid];
    together(&client, &path_of("naked"), args.requests, pids).await?;
    lift_pages(&client, &key, pids).await?;
    relay.kill().await;
    for mut daemon in daemons.into_iter().chain([held]) {
        daemon.stop(Duration::from_secs(5)).await;
    }
    Ok(())
}

fn database_url(args: &PortalBench, dir: &Path) -> String {
    args.database
        .clone()
        .unwrap_or_else(|| format!("sqlite://{}", dir.join("bench.db").display()))
}

/// `canlift-bench portal`.
pub async fn run(args: PortalBench) -> anyhow::Result<()> {
    let dir = tempfile::Builder::new()
        .prefix("canlift-bench-portal-")
        .tempdir()?;
    let result = measure(&args, dir.path()).await;
    result
}

async fn measure(args: &PortalBench, dir: &Path) -> anyhow::Result<()> {
    let url = database_url(args, dir);
    let store = cloud_store::Store::open(&url).await?;
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
    let mut portal = PortalProcess::start(dir, &url, args.portal_cpus.clone()).await?;
    let outcome = async {
        for phase in &args.phases {
            match phase {
                Phase::Idle => idle(args, &portal, dir).await?,
                Phase::Storm => storm(args, &mut portal, dir, &url).await?,
                Phase::Ingest => {
                    ingest(args, &portal, dir).await?;
                }
                Phase::Latency => latency(args, &portal, dir).await?,
                Phase::Curves => curves::curves(args, &portal, dir, &args.curves).await?,
            }
        }
        anyhow::Ok(())
    }
    .await;
    portal.stop().await;
    outcome
}
