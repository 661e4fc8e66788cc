//! `canlift time`: send the TIME object (CiA 301 §7.2.6) so nodes can set their clocks:
//! the system's time now, or a given one, once or at an interval.

use std::time::{Duration, SystemTime};

use anyhow::Context;
use canbus::Bus;
use canopen::time::{TimeOfDay, TIME_COB_ID};
use canopen::types::{self, DataType, Value};

/// Command-line arguments of `canlift time`.
#[derive(Debug, clap::Args)]
pub struct TimeArgs {
    #[command(flatten)]
    bus: super::BusArg,
    /// This time (UTC, `2026-11-23T10:11:12.345`) instead of the system's.
    #[arg(long)]
    at: Option<String>,
    /// Send again every this many seconds (the system's time each time) until Ctrl-C.
    #[arg(long)]
    every_s: Option<u64>,
}

fn stamp(at: Option<&str>) -> anyhow::Result<TimeOfDay> {
    match at {
        Some(text) => match types::from_text(DataType::TimeOfDay, text)? {
            Value::Time { ms, days } => Ok(TimeOfDay { days, ms }),
            _ => anyhow::bail!("{text:?} is not a time of day"),
        },
        None => TimeOfDay::from_system(SystemTime::now())
            .context("the system clock is outside what TIME can carry (1984–2163)"),
    }
}

/// Send TIME once, or at an interval.
pub async fn run(args: TimeArgs) -> anyhow::Result<()> {
    let bus = Bus::open(&args.bus.url)
        .await
        .with_context(|| format!("opening {}", args.bus.url))?;
    let send = async {
        loop {
            let t = stamp(args.at.as_deref())?;
            bus.send(t.frame(TIME_COB_ID)).await?;
            bus.sender.flush().await?;
            let text = types::to_text(
                DataType::TimeOfDay,
                &Value::Time {
                    ms: t.ms,
                    days: t.days,
                },
            );
            println!("TIME {text} UTC");
            match args.every_s {
                Some(s) => tokio::time::sleep(Duration::from_secs(s.max(1))).await,
                None => return anyhow::Ok(()),
            }
        }
    };
    tokio::select! {
        result = send => result,
        signal = tokio::signal::ctrl_c() => signal.context("waiting for Ctrl-C"),
    }
}
