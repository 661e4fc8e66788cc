//! `canlift-bench`: canlift's components measured as they run — the hub, SDO, a node, the
//! elevator gateway, the portal alone and as a cluster, its telemetry writer and alarm service
//! (docs/BENCHMARKS.md). Not part of the product: the daemons measured are the `canlift`
//! binary's, started as processes of their own (`--canlift PATH`, by default the `canlift`
//! beside this binary), so that their CPU time and memory are theirs alone.

mod alarms;
mod bus;
mod cluster;
mod gateway;
mod gets;
mod ingest;
mod least;
mod plot;
mod portal;
mod process;
mod relay;
mod reports;

use std::path::PathBuf;
use std::sync::OnceLock;

use anyhow::Context;
use clap::{Parser, Subcommand};
use tracing_subscriber::filter::Targets;
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::Layer;

/// canlift-bench — how fast, how small and at what cost canlift's components run.
#[derive(Debug, Parser)]
#[command(name = "canlift-bench", version, about, long_about = None)]
struct Cli {
    /// The canlift binary whose daemons are measured [default: `canlift` beside this binary].
    #[arg(long, global = true)]
    canlift: Option<PathBuf>,
    #[command(subcommand)]
    what: Bench,
}

#[derive(Debug, Subcommand)]
enum Bench {
    /// Frames/s, latency and CPU per frame through the hub.
    Hub(bus::HubBench),
    /// SDO transfer rates through the hub, canlift's client and python-canopen's on one server.
    Sdo(bus::SdoBench),
    /// A LocalNode through the hub: change→TPDO latency, PDO frames/s, SYNC jitter, idle CPU.
    Node(bus::NodeBench),
    /// The elevator gateway from a portal's seat: get latency and rate, notifications/s, RSS.
    Gateway(gateway::GatewayBench),
    /// The cloud portal: idle gateways and memory per connection, reconnect storm, ingest,
    /// operator latency.
    Portal(portal::PortalBench),
    /// The portal's cost per bus event: alarm rules, and the alarm service with its database.
    Alarms(alarms::AlarmsBench),
    /// An account's availability and monthly reports over a month of 10,000 lifts.
    Reports(reports::ReportsBench),
    /// The portal's telemetry writer alone: values/s stored and CPU per value.
    Ingest(ingest::IngestBench),
    /// The portal as a cluster: NATS, portal processes on PostgreSQL, load generators.
    Cluster(cluster::ClusterBench),
    /// A process that copies TCP bytes both ways and does nothing else (`portal`'s measure of
    /// what one more process in a request's path costs at the least).
    #[command(hide = true)]
    Relay(relay::RelayArgs),
}

/// The `canlift` binary measured (`--canlift`).
static CANLIFT: OnceLock<PathBuf> = OnceLock::new();

/// The `canlift` binary whose daemons the benchmarks start.
pub(crate) fn canlift() -> anyhow::Result<PathBuf> {
    let path = match CANLIFT.get() {
        Some(path) => path.clone(),
        None => std::env::current_exe()
            .context("locating canlift-bench")?
            .with_file_name("canlift"),
    };
    if !path.exists() {
        anyhow::bail!(
            "{} is missing: build it (`cargo build --release -p canlift`) or name one with --canlift",
            path.display()
        );
    }
    Ok(path)
}

/// Warnings on stderr unless `RUST_LOG` says otherwise; the alarm benchmark does not log each
/// alarm it raises.
fn init_logging() {
    let targets: Targets = std::env::var("RUST_LOG")
        .ok()
        .and_then(|directives| directives.parse().ok())
        .unwrap_or_else(|| {
            Targets::new()
                .with_default(tracing::Level::WARN)
                .with_target("cloud::alarms::service", tracing::Level::ERROR)
        });
    tracing_subscriber::registry()
        .with(
            tracing_subscriber::fmt::layer()
                .with_writer(std::io::stderr)
                .with_filter(targets),
        )
        .init();
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    let cli = Cli::parse();
    init_logging();
    if let Some(path) = cli.canlift {
        let _ = CANLIFT.set(path);
    }
    match cli.what {
        Bench::Hub(h) => bus::run_hub_bench(h).await,
        Bench::Sdo(s) => bus::run_sdo_bench(s).await,
        Bench::Node(n) => bus::run_node_bench(n).await,
        Bench::Gateway(g) => gateway::run(g).await,
        Bench::Portal(p) => portal::run(p).await,
        Bench::Alarms(a) => alarms::run(a).await,
        Bench::Ingest(i) => ingest::run(i).await,
        Bench::Reports(r) => reports::run(r).await,
        Bench::Cluster(c) => cluster::run(c).await,
        Bench::Relay(r) => relay::relay(r).await,
    }
}
