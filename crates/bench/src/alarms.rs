//! `canlift-bench alarms`: what a bus event costs the portal (docs/PORTAL.md §Alarms) — the
//! alarm rules alone (evaluation and the index of active alarms, per event), and the whole
//! alarm service (events stored in batches, alarms raised and cleared in the database) on SQLite
//! in a temporary directory or on a given database.

use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use cloud::alarms::rules::{Active, Applied, Rules};
use cloud::alarms::{service, Alarms};
use cloud::gateways::reports::Report;
use cloud::gateways::Registry;
use cloud_store::Store;
use nxg::msg::{format_time, Event, NodeId, NodeRef, NodeState};

/// Arguments of `canlift-bench alarms`.
#[derive(Debug, Clone, clap::Args)]
pub struct AlarmsBench {
    /// Events per measurement.
    #[arg(long, default_value_t = 200_000)]
    events: usize,
    /// Lifts they come from.
    #[arg(long, default_value_t = 1000)]
    lifts: usize,
    /// The portal's database (an empty one); default: SQLite in a temporary directory.
    #[arg(long)]
    database: Option<String>,
}

/// The `i`-th event: per lift a cycle of a fault EMCY, seven repeats of it, the error reset, and
/// seven heartbeat states — one alarm raised and one cleared every 16 events.
fn event(i: usize, lifts: usize) -> (String, Event) {
    let lift = format!("1050-4096-BENCH-{:06}", i % lifts);
    let step = (i / lifts) % 16;
    let node = NodeRef::new(NodeId::new(1).unwrap_or_else(|| unreachable!()), 1);
    let time = format_time(1_795_000_000_000 + i as i64);
    let event = match step {
        0..=7 => Event::Emcy {
            node,
            time,
            code: "0xFF01".into(),
            register: "0x21".into(),
            data: "0000000000".into(),
            text: "Door blocked".into(),
        },
        8 => Event::Emcy {
            node,
            time,
            code: "0x0000".into(),
            register: "0x00".into(),
            data: "0000000000".into(),
            text: "Error reset or no error".into(),
        },
        _ => Event::State {
            node,
            time,
            state: NodeState::Operational,
        },
    };
    (lift, event)
}

/// The store a portal benchmark `name` writes to: `database`, or SQLite in a temporary directory
/// (removed with the directory returned); its URL.
pub(crate) async fn scratch_store(
    name: &str,
    database: Option<&str>,
) -> anyhow::Result<(tempfile::TempDir, String, Store)> {
    let dir = tempfile::Builder::new()
        .prefix(&format!("canlift-bench-{name}-"))
        .tempdir()?;
    let url = database.map_or_else(
        || {
            format!(
                "sqlite://{}",
                dir.path().join(format!("{name}.db")).display()
            )
        },
        str::to_owned,
    );
    let store = Store::open(&url).await?;
    Ok((dir, url, store))
}

/// Run both measurements.
pub async fn run(args: AlarmsBench) -> anyhow::Result<()> {
    let events: Vec<(String, Event)> = (0..args.events).map(|i| event(i, args.lifts)).collect();
    // The rules and the index alone.
    let rules = Rules::default();
    let mut active = Active::default();
    let mut next_id = 0i64;
    let (mut raised, mut cleared) = (0u64, 0u64);
    let started = Instant::now();
    for (lift, event) in &events {
        for verdict in rules.event(lift, event) {
            match active.apply(verdict, || {
                next_id += 1;
                next_id
            }) {
                Applied::Raised { .. } => raised += 1,
                Applied::Cleared(ids) => cleared += ids.len() as u64,
                Applied::Unchanged => {}
            }
        }
    }
    let elapsed = started.elapsed();
    println!(
        "alarm rules            {:.0} ns per event ({} events, {} lifts; {raised} raised, {cleared} cleared)",
        elapsed.as_nanos() as f64 / events.len() as f64,
        events.len(),
        args.lifts
    );
    // The whole service on a database.
    let (_dir, _, store) = scratch_store("alarms", args.database.as_deref()).await?;
    let (reports, reports_rx) = tokio::sync::mpsc::channel(65536);
    let (acknowledged, acknowledged_rx) = tokio::sync::mpsc::channel(1);
    let (_trends, trends_rx) = tokio::sync::mpsc::channel(1);
    let alarms = Arc::new(Alarms {
        store,
        registry: Arc::new(Registry::default()),
        acknowledged,
        webhooks: Vec::new(),
        outbox: Arc::default(),
        counters: Arc::default(),
    });
    let task = tokio::spawn(service::run(
        alarms.clone(),
        rules,
        Duration::from_secs(3600),
        reports_rx,
        acknowledged_rx,
        trends_rx,
    ));
    let started = Instant::now();
    for (lift, event) in events.iter().cloned() {
        // Waiting for room: the measurement counts stored events, not dropped ones.
        reports.send(Report::Event { lift, event }).await?;
    }
    let counters = alarms.counters.clone();
    while counters.events_stored.load(Ordering::Relaxed)
        + counters.events_dropped.load(Ordering::Relaxed)
        < events.len() as u64
    {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let elapsed = started.elapsed();
    println!(
        "alarm service          {:.0} events/s stored, {:.1} µs per event ({} raised, {} cleared in the database, {} dropped) on {}",
        events.len() as f64 / elapsed.as_secs_f64(),
        elapsed.as_secs_f64() * 1e6 / events.len() as f64,
        counters.raised.load(Ordering::Relaxed),
        counters.cleared.load(Ordering::Relaxed),
        counters.events_dropped.load(Ordering::Relaxed),
        if args.database.is_some() { "the given database" } else { "SQLite" }
    );
    drop(reports);
    task.abort();
    Ok(())
}
