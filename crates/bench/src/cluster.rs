//! `canlift-bench cluster`: the portal as a cluster (docs/CLUSTER.md) under load. Starts a NATS
//! server (Debian's `nats-server -js`, on a free loopback port), P `canlift cloud` processes on
//! one PostgreSQL database (an existing URL) and enough `canlift loadgen` processes — each
//! under the per-process file limit, spread over loopback source addresses — to connect N
//! gateways, each load generator to one portal process in turn (as a load balancer would).
//!
//! Figures: time until all N are online (held by some process, known to every other), the
//! portals' memory per connection, the CPU the portals and NATS spend holding them while
//! nothing happens, operator reads of a lift held by the process asked vs by another (what
//! NATS adds) beside a bare NATS request and reply (the least it can add here), and the time until every lift of a process killed with SIGKILL (and started
//! again, as systemd's `Restart=always` does) is online again.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use futures_util::StreamExt;

use crate::portal::{bench_config, lift_id, metric, PortalProcess};
use crate::process::cpu_time;
use crate::process::listening;
use crate::process::{memory_kib, percentile, Daemon};

/// Arguments of `canlift-bench cluster`.
#[derive(Debug, Clone, clap::Args)]
pub struct ClusterBench {
    /// The processes' shared database: `postgres://…` (a cluster needs PostgreSQL), a fresh
    /// one (the gateways' serial numbers are the same in every run).
    #[arg(long)]
    database: String,
    /// Portal processes.
    #[arg(long, default_value_t = 6)]
    portals: usize,
    /// Gateways in all.
    #[arg(long, default_value_t = 100_000)]
    gateways: usize,
    /// Gateways per load-generator process at most (each holds one file per gateway, under
    /// the per-process limit); the load generators are a multiple of the portal processes, so
    /// each process gets the same share.
    #[arg(long, default_value_t = 16_000)]
    per_loadgen: usize,
    /// First-contact connections per second per load generator.
    #[arg(long, default_value_t = 1000)]
    rate: u32,
    /// Loopback source addresses per load generator (127.0.0.1…127.0.0.N).
    #[arg(long, default_value_t = 8)]
    sources: u8,
    /// Operator reads for each latency figure.
    #[arg(long, default_value_t = 1000)]
    reads: usize,
    /// `[cluster] holder_ttl_s` of the portals.
    #[arg(long, default_value_t = 30)]
    holder_ttl_s: u64,
    /// The NATS server binary.
    #[arg(long, default_value = "nats-server")]
    nats_server: PathBuf,
    /// Threads the NATS server runs Go code on at once (`GOMAXPROCS`; 0: Go's default, one per
    /// core). One, where NATS shares two cores with the portals, costs a relayed read less of
    /// NATS's CPU and time (docs/CLUSTER.md §NATS on a machine it shares).
    #[arg(long, default_value_t = 0)]
    nats_threads: u16,
    /// NATS servers forming one NATS cluster; the portals list them all and keep the holder
    /// bucket in as many copies (at most 5) (docs/CLUSTER.md §A NATS of several servers).
    #[arg(long, default_value_t = 1)]
    nats_servers: usize,
    /// NATS with TLS (a certificate of the benchmark's CA; the portals trust it by `nats_ca`),
    /// to measure what TLS on the relays costs (docs/CLUSTER.md §Securing NATS).
    #[arg(long)]
    nats_tls: bool,
    /// Seconds to wait after the reads before process 0 is killed: its restart then falls
    /// after the roll-ups of the values the first contacts brought, not beside them
    /// (docs/BENCHMARKS.md §First contact on a durable PostgreSQL).
    #[arg(long, default_value_t = 0)]
    settle_s: u64,
}

/// How long the cluster's own cost is measured with every gateway online and no operator
/// asking: what holding the lifts costs (leases renewed, the gateways' keep-alives).
const IDLE_WINDOW: Duration = Duration::from_secs(20);

/// The NATS server of the benchmark, or the servers of its NATS cluster.
struct Nats {
    children: Vec<tokio::process::Child>,
    urls: Vec<String>,
    /// With TLS: the CA its clients trust.
    ca: Option<PathBuf>,
}

impl Nats {
    async fn start(
        args: &ClusterBench,
        dir: &Path,
        pki: &cloud::devpki::DevPki,
    ) -> anyhow::Result<Nats> {
        let (binary, threads, servers) = (&args.nats_server, args.nats_threads, args.nats_servers);
        let ports = (0..servers)
            .map(|_| testkit::free_port())
            .collect::<Vec<_>>();
        let routes = (0..servers)
            .map(|_| testkit::free_port())
            .collect::<Vec<_>>();
        let all_routes = routes
            .iter()
            .map(|port| format!("nats://127.0.0.1:{port}"))
            .collect::<Vec<_>>()
            .join(",");
        let mut children = Vec::with_capacity(servers);
        for (i, port) in ports.iter().enumerate() {
            let mut command = tokio::process::Command::new(binary);
            if threads > 0 {
                command.env("GOMAXPROCS", threads.to_string());
            }
            command
                .args(["-js", "-a", "127.0.0.1", "-p", &port.to_string(), "-sd"])
                .arg(dir.join(format!("n{i}")));
            if args.nats_tls {
                command
                    .arg("--tls")
                    .arg("--tlscert")
                    .arg(&pki.cert)
                    .arg("--tlskey")
                    .arg(&pki.key);
            }
            if servers > 1 {
                command
                    .args(["--server_name", &format!("n{i}"), "--cluster_name", "bench"])
                    .args(["--cluster", &format!("nats://127.0.0.1:{}", routes[i])])
                    .args(["--routes", &all_routes]);
            }
            let child = command
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::null())
                .kill_on_drop(true)
                .spawn()
                .with_context(|| format!("{} (apt-get install nats-server)", binary.display()))?;
            children.push(child);
        }
        for port in &ports {
            listening(*port, "nats-server", Duration::from_secs(10)).await?;
        }
        let scheme = if args.nats_tls { "tls" } else { "nats" };
        Ok(Nats {
            children,
            urls: ports
                .iter()
                .map(|port| format!("{scheme}://127.0.0.1:{port}"))
                .collect(),
            ca: args.nats_tls.then(|| pki.ca.clone()),
        })
    }

    /// A client of server `url`, connected as the portals connect (`[cluster] nats_ca`).
    async fn client(&self, url: &str) -> anyhow::Result<async_nats::Client> {
        let section = cloud_cluster::ClusterSection {
            nats_ca: self.ca.clone(),
            ..Default::default()
        };
        let access = cloud_cluster::nats::NatsAccess::from_config(&section, url)?;
        let options = access.options();
        Ok(options.connect(access.servers()).await?)
    }

    /// `[cluster] nats`: every server.
    fn url(&self) -> String {
        self.urls.join(",")
    }

    fn rss_kib(&self) -> u64 {
        self.children
            .iter()
            .filter_map(|c| c.id().and_then(memory_kib))
            .map(|m| m[0])
            .sum()
    }

    fn cpu(&self) -> Duration {
        self.children
            .iter()
            .filter_map(|c| c.id().and_then(cpu_time))
            .sum()
    }
}

/// The portal processes, each with its configuration.
struct Portals {
    processes: Vec<PortalProcess>,
    configs: Vec<(PathBuf, cloud::config::Config)>,
    ca: PathBuf,
}

impl Portals {
    /// The lifts held in all, and whether they are `n` and each process knows all `n`.
    async fn count(&self, n: usize) -> anyhow::Result<(usize, bool)> {
        // All at once, one scrape each: a busy process does not hold up the others' answers.
        let scraped = futures_util::future::join_all(self.processes.iter().map(|p| p.scrape()));
        let (mut held, mut known) = (0, Vec::with_capacity(self.processes.len()));
        for scraped in scraped.await {
            let scraped = scraped?;
            let here = metric(&scraped, "canlift_cluster_lifts_held")? as usize;
            held += here;
            known.push(here + metric(&scraped, "canlift_cluster_lifts_elsewhere")? as usize);
        }
        Ok((held, held == n && known.iter().all(|&k| k == n)))
    }

    /// Wait until the processes hold `n` lifts together and each knows the others'; how long.
    async fn all_held(
        &self,
        n: usize,
        since: Instant,
        limit: Duration,
    ) -> anyhow::Result<Duration> {
        let (mut last_report, mut held) = (Instant::now(), 0);
        loop {
            // A process too busy to answer in time is asked again on the next round; the count
            // reported meanwhile is the last one all processes gave.
            let everywhere = match self.count(n).await {
                Ok((now_held, everywhere)) => {
                    held = now_held;
                    everywhere
                }
                Err(e) => {
                    println!("  a process did not answer: {e:#}");
                    false
                }
            };
            if everywhere {
                return Ok(since.elapsed());
            }
            if since.elapsed() > limit {
                bail!("{held} of {n} lifts held after {limit:?}");
            }
            if last_report.elapsed() > Duration::from_secs(5) {
                println!("  {held} held after {:.0} s", since.elapsed().as_secs_f64());
                last_report = Instant::now();
            }
            tokio::time::sleep(Duration::from_millis(250)).await;
        }
    }

    fn rss_kib(&self) -> u64 {
        self.processes.iter().map(PortalProcess::rss_kib).sum()
    }

    /// The processes' CPU time so far, together.
    fn cpu(&self) -> Duration {
        self.processes
            .iter()
            .filter_map(|p| cpu_time(p.daemon.pid))
            .sum()
    }
}

/// How the gateways are spread: `loadgens` load generators (a multiple of the portal
/// processes) of `per` gateways each (the last one fewer); load generator `j` connects to
/// process `j % portals`.
#[derive(Debug, Clone, Copy)]
struct Layout {
    loadgens: usize,
    per: usize,
    portals: usize,
}

impl Layout {
    fn new(args: &ClusterBench) -> Layout {
        let loadgens = args
            .gateways
            .div_ceil(args.per_loadgen)
            .next_multiple_of(args.portals)
            .min(args.gateways.max(1));
        Layout {
            loadgens,
            per: args.gateways.div_ceil(loadgens),
            portals: args.portals,
        }
    }

    /// The process holding gateway `number` (from 1).
    fn holder(&self, number: usize) -> usize {
        ((number - 1) / self.per) % self.portals
    }
}

/// `reads` gets of 0x652001, each of a lift held by process `h` asked of process `ask(h)`;
/// their times, sorted.
async fn reads(
    args: &ClusterBench,
    layout: Layout,
    portals: &Portals,
    key: &str,
    ask: impl Fn(usize) -> usize,
) -> anyhow::Result<Vec<Duration>> {
    let mut connections = Vec::new();
    for p in &portals.processes {
        let url = format!("https://localhost:{}", p.port);
        let client = cloud::client::Client::new(&url, Some(key), Some(&portals.ca))?;
        connections.push(client.connect().await?);
    }
    let mut times = Vec::with_capacity(args.reads);
    for k in 0..args.reads {
        let number = 1 + (k * 7919) % args.gateways;
        let holder = layout.holder(number);
        let path = format!(
            "/api/v1/lifts/{}/objects/0x652001?form=naked",
            lift_id(number)
        );
        let begin = Instant::now();
        let (status, body) = connections[ask(holder)].call("GET", &path, None).await?;
        times.push(begin.elapsed());
        if status != 200 {
            bail!("GET {path}: {status} {body}");
        }
    }
    times.sort();
    Ok(times)
}

/// A bare request and reply of 200 bytes between two NATS clients through the benchmark's
/// server, `n` times: the least NATS adds to a relayed read on this machine (each client's hops
/// and the server's, no portal). With a NATS cluster the two are on different servers (as two
/// portal processes may be), which adds the route between them.
async fn nats_round_trips(nats: &Nats, n: usize) -> anyhow::Result<Vec<Duration>> {
    let (Some(first), Some(last)) = (nats.urls.first(), nats.urls.last()) else {
        bail!("no NATS server");
    };
    let replier = nats.client(first).await?;
    let mut asked = replier.subscribe("bench.echo").await?;
    replier.flush().await?;
    let answering = tokio::spawn(async move {
        while let Some(message) = asked.next().await {
            if let Some(reply) = message.reply {
                let _ = replier.publish(reply, message.payload).await;
            }
        }
    });
    let asker = nats.client(last).await?;
    let payload = vec![b'x'; 200];
    let mut times = Vec::with_capacity(n);
    for _ in 0..n {
        let begin = Instant::now();
        asker.request("bench.echo", payload.clone().into()).await?;
        times.push(begin.elapsed());
    }
    answering.abort();
    times.sort();
    Ok(times)
}

/// `canlift-bench cluster`.
pub async fn run(args: ClusterBench) -> anyhow::Result<()> {
    if !args.database.starts_with("postgres") {
        bail!("--database: a cluster needs PostgreSQL (postgres://…)");
    }
    if args.portals == 0 || args.per_loadgen == 0 || args.gateways == 0 {
        bail!("--portals, --per-loadgen and --gateways: at least 1");
    }
    let layout = Layout::new(&args);
    let dir = tempfile::tempdir()?;
    if !(1..=32).contains(&args.nats_servers) {
        bail!("--nats-servers: 1 to 32");
    }
    let pki = cloud::devpki::ensure(&dir.path().join("pki"))?;
    let nats = Nats::start(&args, &dir.path().join("nats"), &pki).await?;
    let store = cloud_store::Store::open(&args.database).await?;
    let domain = "CLUSTER".to_owned();
    if store.domain_exists(&domain).await? {
        bail!(
            "{} already has the CLUSTER account: give a fresh database",
            args.database
        );
    }
    let key = store.add_account("bench-cluster", &domain).await?;
    // Every process's pools within what PostgreSQL takes (beyond, it refuses the connections
    // the pools open under load, each refusal a process start of its own).
    let free = store.free_connections().await?.unwrap_or(0);
    let per_process = free / i64::try_from(args.portals)? - 2;
    let connections = u32::try_from(per_process.clamp(0, 16))?;
    if connections < 2 {
        bail!(
            "PostgreSQL takes {free} more connections: too few for {} portal processes \
             (raise max_connections)",
            args.portals
        );
    }
    let mut portals = Portals {
        processes: Vec::new(),
        configs: Vec::new(),
        ca: pki.ca.clone(),
    };
    for i in 0..args.portals {
        let pdir = dir.path().join(format!("p{i}"));
        let mut config = bench_config(&pdir, &args.database)?;
        config.server.tls_cert = Some(pki.cert.clone());
        config.server.tls_key = Some(pki.key.clone());
        config.cluster.nats = Some(nats.url());
        config.cluster.nats_replicas = args.nats_servers.min(5);
        config.cluster.nats_ca = nats.ca.clone();
        config.cluster.node = Some(format!("bench-{i}"));
        config.cluster.holder_ttl_s = args.holder_ttl_s;
        config.database.connections = connections;
        portals
            .processes
            .push(PortalProcess::start_with(&pdir, &config, pki.ca.clone(), None).await?);
        portals.configs.push((pdir, config));
    }
    tokio::time::sleep(Duration::from_secs(1)).await;
    let (base_rss, base_nats) = (portals.rss_kib(), nats.rss_kib());
    println!(
        "{} portal processes ({connections} + 2 PostgreSQL connections each of {free} free), \
         NATS {} ({}), {} gateways from {} load generators of at most {}",
        args.portals,
        nats.url(),
        match args.nats_threads {
            0 => "GOMAXPROCS as Go chooses".to_owned(),
            n => format!("GOMAXPROCS={n}"),
        },
        args.gateways,
        layout.loadgens,
        layout.per
    );
    let exe = crate::canlift()?;
    let begin = Instant::now();
    let mut loadgens = Vec::new();
    for (j, first) in (1..=args.gateways).step_by(layout.per).enumerate() {
        let n = layout.per.min(args.gateways + 1 - first);
        let portal = &portals.processes[j % args.portals];
        let url = format!("wss://localhost:{}/ws", portal.port);
        let state = dir.path().join(format!("loadgen-{j}"));
        let argv: Vec<std::ffi::OsString> = vec![
            "loadgen".into(),
            "--portal".into(),
            url.into(),
            "--ca".into(),
            pki.ca.clone().into(),
            "--domain".into(),
            domain.clone().into(),
            "--gateways".into(),
            n.to_string().into(),
            "--first".into(),
            first.to_string().into(),
            "--sources".into(),
            args.sources.to_string().into(),
            "--rate".into(),
            args.rate.to_string().into(),
            "--state".into(),
            state.into(),
        ];
        let argv: Vec<&std::ffi::OsStr> = argv.iter().map(|a| a.as_os_str()).collect();
        loadgens.push(Daemon::spawn(&exe, &argv, std::process::Stdio::null())?);
    }
    let limit = Duration::from_secs(1800);
    let online = portals.all_held(args.gateways, begin, limit).await?;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let rss = portals.rss_kib().saturating_sub(base_rss);
    let nats_rss = nats.rss_kib().saturating_sub(base_nats);
    println!(
        "all {} online (held once, known everywhere) after {:.1} s",
        args.gateways,
        online.as_secs_f64()
    );
    println!(
        "portal memory: {:.1} KiB per connection ({} MiB over {} processes); NATS {:.2} KiB per lift",
        rss as f64 / args.gateways as f64,
        rss / 1024,
        args.portals,
        nats_rss as f64 / args.gateways as f64
    );
    // One scrape per process for every total below.
    let mut totals = [0.0; 6];
    for p in &portals.processes {
        let scraped = p.scrape().await?;
        for (sum, name) in totals.iter_mut().zip([
            "canlift_gateways_admitted_total",
            "canlift_gateways_refused_total",
            "canlift_gateways_registry_unavailable_total",
            "canlift_admission_lookups_total",
            "canlift_cluster_events_unwatched_total",
            "canlift_cluster_entries_swept_total",
        ]) {
            *sum += metric(&scraped, name)?;
        }
    }
    let [admitted, refused, unavailable, lookups, unwatched, swept] = totals;
    println!(
        "CONNECTs: {admitted:.0} admitted, {refused:.0} refused, {unavailable:.0} refused \
         \"registry unavailable\"; {lookups:.0} lookups ({:.1} CONNECTs each)",
        (admitted + refused + unavailable) / lookups.max(1.0)
    );
    println!(
        "live events kept off NATS (no other process watched their lift): {unwatched:.0}, {:.1} per gateway",
        unwatched / args.gateways as f64
    );
    // No process has died yet: every entry swept was a living holder's (taken for dead).
    println!("holder entries swept while every process lived: {swept:.0}");
    let idle = IDLE_WINDOW.as_secs_f64();
    let before = (portals.cpu(), nats.cpu());
    tokio::time::sleep(IDLE_WINDOW).await;
    let (portal_cpu, nats_cpu) = (
        portals.cpu().saturating_sub(before.0).as_secs_f64() / idle,
        nats.cpu().saturating_sub(before.1).as_secs_f64() / idle,
    );
    println!(
        "all online, nobody asking ({idle:.0} s): portals {:.1} % of a core, NATS {:.1} %; \
         {:.2} µs of CPU per lift per second",
        portal_cpu * 100.0,
        nats_cpu * 100.0,
        (portal_cpu + nats_cpu) * 1e6 / args.gateways as f64
    );
    let others = args.portals;
    let cpu = || (portals.cpu(), nats.cpu());
    let before = cpu();
    let local = reads(&args, layout, &portals, &key, |h| h).await?;
    let between = cpu();
    let remote = reads(&args, layout, &portals, &key, |h| (h + 1) % others).await?;
    let after = cpu();
    let (l50, l99) = (percentile(&local, 50.0), percentile(&local, 99.0));
    let (r50, r99) = (percentile(&remote, 50.0), percentile(&remote, 99.0));
    println!(
        "operator reads ({} each): held by the process asked p50 {l50:.0} µs p99 {l99:.0} µs; \
         held by another p50 {r50:.0} µs p99 {r99:.0} µs; NATS adds {:.0} µs at p50",
        args.reads,
        r50 - l50
    );
    let per_read = |from: Duration, to: Duration| {
        to.saturating_sub(from).as_secs_f64() * 1e6 / args.reads as f64
    };
    println!(
        "CPU per read: held by the process asked: portals {:.0} µs; held by another: portals \
         {:.0} µs, NATS {:.0} µs",
        per_read(before.0, between.0),
        per_read(between.0, after.0),
        per_read(between.1, after.1)
    );
    let bare = nats_round_trips(&nats, args.reads).await?;
    println!(
        "a bare NATS request and reply (two clients, 200 bytes): p50 {:.0} µs p99 {:.0} µs",
        percentile(&bare, 50.0),
        percentile(&bare, 99.0)
    );
    if args.portals > 1 {
        tokio::time::sleep(Duration::from_secs(args.settle_s)).await;
        let victim = portals.processes.remove(0);
        let (pdir, config) = portals.configs[0].clone();
        let killed = Instant::now();
        victim.daemon.kill().await;
        let restarted = PortalProcess::start_with(&pdir, &config, pki.ca.clone(), None).await?;
        portals.processes.insert(0, restarted);
        let back = portals.all_held(args.gateways, killed, limit).await?;
        println!(
            "process 0 killed (SIGKILL) and started again: all {} online again after {:.1} s",
            args.gateways,
            back.as_secs_f64()
        );
    }
    for mut loadgen in loadgens {
        loadgen.stop(Duration::from_secs(30)).await;
    }
    for p in portals.processes {
        p.stop().await;
    }
    drop(nats);
    Ok(())
}
