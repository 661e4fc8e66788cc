//! `canlift-bench ingest`: the portal's telemetry writer alone (docs/BENCHMARKS.md §Ingest) —
//! values handed to it as fast as it takes them, written in its batches to SQLite in a
//! temporary directory or to a given database. It measures the database path, without the TLS,
//! WebSocket and JSON work in front of it that `bench portal` includes.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::bail;
use cloud::gateways::{telemetry, TelemetryCounters};
use cloud_store::TelemetryRow;

use crate::process::cpu_time;

/// Arguments of `canlift-bench ingest`.
#[derive(Debug, Clone, clap::Args)]
pub struct IngestBench {
    /// Values per run.
    #[arg(long, default_value_t = 500_000)]
    values: usize,
    /// Lifts they come from.
    #[arg(long, default_value_t = 1000)]
    lifts: usize,
    /// Runs (each on the growing table).
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// The portal's database (an empty one); default: SQLite in a temporary directory.
    #[arg(long)]
    database: Option<String>,
}

/// The `i`-th value: lifts in turn, the four objects a moving lift pushes.
fn row(i: usize, lifts: usize, at: i64) -> TelemetryRow {
    const OBJECTS: [&str; 4] = ["0x652001", "0x638301", "0x639001", "0x648001"];
    TelemetryRow {
        lift: format!("1050-4097-LOAD-{:06}", i % lifts),
        mplex: OBJECTS[(i / lifts) % 4].to_owned(),
        node: 1,
        value: (i % 20_000).to_string(),
        at,
    }
}

/// Roll up what was stored until `last` (ms) as the portal's roll-up task does, round by
/// round, and print what it cost per value (docs/PORTAL.md §History).
async fn roll_up(store: &cloud_store::Store, last: i64) -> anyhow::Result<()> {
    // Past the last value's minute and the roll-ups' lag behind the newest values.
    let now = last + 5 * 60_000;
    let cpu0 = cpu_time(std::process::id()).unwrap_or_default();
    let started = Instant::now();
    let (mut values, mut rows) = (0, 0);
    loop {
        let round = store.roll_up(now).await?;
        if round.values == 0 {
            break;
        }
        values += round.values;
        rows += round.minutes + round.hours;
    }
    let elapsed = started.elapsed();
    let cpu = cpu_time(std::process::id())
        .unwrap_or_default()
        .saturating_sub(cpu0);
    println!(
        "  roll-ups: {values} values into {rows} minute and hour rows in {:.2} s: {:.2} µs per value, portal side {:.2} µs CPU",
        elapsed.as_secs_f64(),
        elapsed.as_secs_f64() * 1e6 / values.max(1) as f64,
        cpu.as_secs_f64() * 1e6 / values.max(1) as f64
    );
    Ok(())
}

/// `canlift-bench ingest`.
pub async fn run(args: IngestBench) -> anyhow::Result<()> {
    let (_dir, url, store) =
        crate::alarms::scratch_store("ingest", args.database.as_deref()).await?;
    let kind = if url.starts_with("postgres") {
        "PostgreSQL"
    } else {
        "SQLite"
    };
    for run in 1..=args.runs {
        // Each run an hour after the one before: its roll-up reads its own values alone.
        let base = cloud_types::now_ms() + (run as i64 - 1) * 3_600_000;
        let rows: Vec<TelemetryRow> = (0..args.values)
            .map(|i| row(i, args.lifts.max(1), base + i as i64))
            .collect();
        // The portal's queue in front of the writer; a full one makes this wait, so every value
        // is stored and the rate is the writer's.
        let (tx, rx) = tokio::sync::mpsc::channel(65_536);
        let counters = Arc::new(TelemetryCounters::default());
        let (_stop, stopping) = tokio::sync::watch::channel(false);
        let writer = tokio::spawn(telemetry::writer(
            store.clone(),
            rx,
            counters.clone(),
            stopping,
            Default::default(),
        ));
        let cpu0 = cpu_time(std::process::id()).unwrap_or_default();
        let started = Instant::now();
        for row in rows {
            tx.send(row).await?;
        }
        drop(tx);
        writer.await?;
        let elapsed = started.elapsed();
        let cpu = cpu_time(std::process::id())
            .unwrap_or_default()
            .saturating_sub(cpu0);
        let (stored, dropped) = (
            counters.stored.load(Ordering::Relaxed),
            counters.dropped_total(),
        );
        if dropped > 0 || stored != args.values as u64 {
            bail!("{stored} stored, {dropped} dropped of {}", args.values);
        }
        println!(
            "ingest on {kind:<10}  run {run}: {:.0} values/s stored, portal side {:.2} µs CPU per value ({} values in {:.2} s)",
            stored as f64 / elapsed.as_secs_f64(),
            cpu.as_secs_f64() * 1e6 / stored as f64,
            stored,
            elapsed.as_secs_f64()
        );
        roll_up(&store, base + args.values as i64).await?;
        tokio::time::sleep(Duration::from_millis(200)).await;
    }
    Ok(())
}
