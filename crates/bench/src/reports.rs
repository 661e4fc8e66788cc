//! `canlift-bench reports`: what an account's availability report costs (docs/PORTAL.md
//! §Availability): a month of a 10,000-lift account — its status changes, faults and counters
//! written into a fresh database — answered as the API answers it, three times, with the
//! database's plan of each statement.

use std::time::Instant;

use cloud::config::InsightsSection;
use cloud::insights::{self, Month};
use cloud_store::{GatewayRecord, Lifts, Statement, StatusRow, TelemetryRow};
use cloud_types::alarms::{Alarm, Condition, Kind, Place, Severity};
use cloud_types::insights::Status;

/// Arguments of `canlift-bench reports`.
#[derive(Debug, Clone, clap::Args)]
pub struct ReportsBench {
    /// Lifts of the account.
    #[arg(long, default_value_t = 10_000)]
    lifts: usize,
    /// Status changes per lift and day.
    #[arg(long, default_value_t = 6)]
    changes_per_day: usize,
    /// Faults per lift and month.
    #[arg(long, default_value_t = 3)]
    faults: usize,
    /// Hours between two stored values of each counter.
    #[arg(long, default_value_t = 6)]
    counter_every_h: i64,
    /// The month reported, `YYYY-MM` (its data and the three months' before are written).
    #[arg(long, default_value = "2026-10")]
    month: String,
    /// Measurements.
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// The portal's database: an empty one is filled, one this benchmark filled before is
    /// measured again; default: SQLite in a temporary directory.
    #[arg(long)]
    database: Option<String>,
}

const DOMAIN: &str = "BEN";
const H: i64 = 3_600_000;

/// Write the account's lifts and four months of their data.
async fn fill(
    store: &cloud_store::Store,
    args: &ReportsBench,
    from: i64,
    to: i64,
) -> anyhow::Result<Vec<String>> {
    store.add_account("bench", DOMAIN).await?;
    let lifts: Vec<String> = (0..args.lifts)
        .map(|i| format!("1050-4096-REPORT-{i:06}"))
        .collect();
    for chunk in lifts.chunks(1000) {
        let records: Vec<GatewayRecord> = chunk
            .iter()
            .map(|lift| {
                let sernum = lift.trim_start_matches("1050-4096-");
                GatewayRecord::connected(lift, &testkit::connect(sernum, DOMAIN, None), 2)
            })
            .collect();
        store.record(&records).await?;
    }
    let days = (to - from) / (24 * H);
    let cycle = [
        Status::InService,
        Status::OutOfService,
        Status::InService,
        Status::Offline,
        Status::Unknown,
    ];
    let step = 24 * H / args.changes_per_day.max(1) as i64;
    let mut statuses = Vec::new();
    let mut alarms = Vec::new();
    let mut values = Vec::new();
    for (n, lift) in lifts.iter().enumerate() {
        let offset = (n as i64 * 7_919) % step;
        for k in 0..days * args.changes_per_day as i64 {
            statuses.push(StatusRow {
                lift: lift.clone(),
                at: from + offset + k * step,
                status: cycle[(k as usize + n) % cycle.len()],
            });
        }
        let month = (to - from) / 4;
        for f in 0..args.faults * 4 {
            let condition = Condition {
                lift: lift.clone(),
                kind: Kind::Emcy,
                place: Some(Place {
                    id: Some(1),
                    net: 1,
                }),
                code: format!("0x{:04X}", 0xFF00 + f),
            };
            let at = from
                + offset
                + (f / args.faults) as i64 * month
                + (f % args.faults) as i64 * 86_400_000;
            alarms.push(Alarm::raised(
                cloud_store::new_id(),
                &condition,
                Severity::Major,
                "fault",
                at,
            ));
        }
        let mut at = from + offset;
        let mut k = 0u64;
        while at < to {
            for (mplex, per) in [("0x652001", 40), ("0x440001", 80), ("0x440004", 3)] {
                values.push(TelemetryRow {
                    lift: lift.clone(),
                    mplex: mplex.into(),
                    node: 0,
                    value: (k * per).to_string(),
                    at,
                });
            }
            at += args.counter_every_h * H;
            k += 1;
        }
        if statuses.len() > 50_000 || n + 1 == lifts.len() {
            store
                .write_alarm_batch(&[], &statuses, &alarms, &[])
                .await?;
            store.telemetry(&values).await?;
            statuses.clear();
            alarms.clear();
            values.clear();
        }
    }
    Ok(lifts)
}

/// Fill the database, then measure.
pub async fn run(args: ReportsBench) -> anyhow::Result<()> {
    let month = Month::parse(&args.month)
        .ok_or_else(|| anyhow::anyhow!("--month {}: YYYY-MM", args.month))?;
    let first = month.previous().previous().previous();
    let (_dir, url, store) =
        super::alarms::scratch_store("reports", args.database.as_deref()).await?;
    let started = Instant::now();
    if store.account("bench").await?.is_some() {
        println!("measuring the lifts filled in before");
    } else {
        fill(&store, &args, first.start(), month.end()).await?;
    }
    println!(
        "filled {} lifts × 4 months ({} status changes/day, {} faults/month, counters every {} h) in {:.1} s",
        args.lifts,
        args.changes_per_day,
        args.faults,
        args.counter_every_h,
        started.elapsed().as_secs_f64()
    );
    let insights = InsightsSection::default()
        .insights()
        .map_err(anyhow::Error::msg)?;
    let lifts = Lifts {
        domain: DOMAIN,
        lift: None,
    };
    let database = if url.starts_with("sqlite") {
        "SQLite"
    } else {
        "PostgreSQL"
    };
    for statement in Statement::ALL {
        println!("plan of {} ({database}):", statement.name());
        for line in store.explain(statement, lifts).await?.lines() {
            println!("    {line}");
        }
    }
    let account = cloud_types::users::Account {
        name: "bench".into(),
        domain: DOMAIN.into(),
    };
    for run in 1..=args.runs {
        let started = Instant::now();
        let figures =
            insights::figures(&store, &insights, lifts, month.start(), month.end()).await?;
        let report = started.elapsed();
        let started = Instant::now();
        let monthly = insights::monthly(&store, &insights, &account, month).await?;
        let whole = started.elapsed();
        println!(
            "run {run}: availability report of {} lifts for {month}: {:.3} s; monthly report (4 months): {:.3} s (availability {:.4})",
            figures.len(),
            report.as_secs_f64(),
            whole.as_secs_f64(),
            monthly.availability.unwrap_or(f64::NAN)
        );
    }
    Ok(())
}
