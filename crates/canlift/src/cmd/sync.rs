//! `canlift sync`: be the network's SYNC producer (CiA 301 §7.2.5) for testing synchronous
//! PDOs: SYNC on COB-ID 80h at a period, optionally with the counter (1019h semantics).

use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use canbus::Bus;
use canopen::sync::{SyncConfig, SyncProducer};

/// Command-line arguments of `canlift sync`.
#[derive(Debug, clap::Args)]
pub struct SyncArgs {
    #[command(flatten)]
    bus: super::BusArg,
    /// The communication cycle period in milliseconds (1006h).
    #[arg(long, default_value_t = 100)]
    period_ms: u64,
    /// Send the SYNC counter, counting 1…OVERFLOW (1019h: 2–240).
    #[arg(long, value_name = "OVERFLOW")]
    counter: Option<u8>,
    /// Stop after this many SYNCs (default: until Ctrl-C).
    #[arg(long)]
    count: Option<u64>,
}

/// Produce SYNC until the count is reached or Ctrl-C.
pub async fn run(args: SyncArgs) -> anyhow::Result<()> {
    if let Some(overflow) = args.counter {
        if !(2..=240).contains(&overflow) {
            bail!("--counter {overflow}: the overflow value is 2–240 (CiA 301 §7.5.2.43)");
        }
    }
    let period_us = u32::try_from(args.period_ms.saturating_mul(1000))
        .ok()
        .filter(|us| *us > 0)
        .context("--period-ms is 1…4294967")?;
    let bus = Bus::open(&args.bus.url)
        .await
        .with_context(|| format!("opening {}", args.bus.url))?;
    let config = SyncConfig {
        cob_id: 0x4000_0080,
        period_us,
        window_us: 0,
        counter_overflow: args.counter.unwrap_or(0),
    };
    let mut producer = SyncProducer::new(config, Instant::now());
    let mut frames = Vec::new();
    let mut sent = 0u64;
    let produce = async {
        while args.count.is_none_or(|n| sent < n) {
            canopen::wake::sleep_until(producer.poll_timeout()).await;
            producer.handle_timeout(Instant::now(), &mut frames);
            for frame in frames.drain(..) {
                bus.send(frame).await?;
                sent += 1;
            }
        }
        bus.sender.flush().await?;
        anyhow::Ok(())
    };
    tokio::select! {
        result = produce => result?,
        signal = tokio::signal::ctrl_c() => signal.context("waiting for Ctrl-C")?,
    }
    eprintln!(
        "{sent} SYNC sent every {:?}",
        Duration::from_micros(period_us.into())
    );
    Ok(())
}
