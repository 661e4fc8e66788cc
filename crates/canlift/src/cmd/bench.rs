//! `canlift bench hub`: throughput, latency and CPU cost of the hub, measured end to end.
//!
//! The hub runs as a separate process (this binary's `hub` subcommand, or one given with
//! `--hub`), so its CPU time can be read from `/proc` apart from the clients'. Clients are
//! canlift `socketcand://` endpoints in this process. Every frame carries its sequence number and
//! send time, so the receivers measure one-way latency and check order and loss.

use std::net::SocketAddr;
use std::process::Stdio;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use canbus::{Bus, BusOptions, CanId, Frame};
use tokio::io::{AsyncBufReadExt, BufReader};

/// Command-line arguments of `canlift bench`.
#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    #[command(subcommand)]
    what: BenchKind,
}

#[derive(Debug, clap::Subcommand)]
enum BenchKind {
    /// Frames/s, latency and CPU per frame through the hub.
    Hub(HubBench),
}

#[derive(Debug, Clone, clap::Args)]
struct HubBench {
    /// Clients on the bus (all receive).
    #[arg(long, default_value_t = 2)]
    clients: usize,
    /// How many of the clients send.
    #[arg(long, default_value_t = 1)]
    senders: usize,
    /// Frames each sender sends.
    #[arg(long, default_value_t = 100_000)]
    frames: u32,
    /// Frames per second per sender; 0 sends as fast as the hub accepts.
    #[arg(long, default_value_t = 0)]
    rate: u32,
    /// Use a running hub at this address instead of starting one (CPU is then not measured).
    #[arg(long)]
    hub: Option<SocketAddr>,
    /// Start the hub with this --bitrate.
    #[arg(long)]
    bitrate: Option<u32>,
}

struct RunningHub {
    addr: SocketAddr,
    child: Option<tokio::process::Child>,
}

async fn start_hub(bitrate: Option<u32>) -> anyhow::Result<RunningHub> {
    let exe = std::env::current_exe().context("locating the canlift binary")?;
    let mut cmd = tokio::process::Command::new(exe);
    cmd.args(["hub", "--listen", "127.0.0.1:0"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .env("RUST_LOG", "warn")
        .kill_on_drop(true);
    if let Some(b) = bitrate {
        cmd.args(["--bitrate", &b.to_string()]);
    }
    let mut child = cmd.spawn().context("starting canlift hub")?;
    let stdout = child.stdout.take().context("hub stdout")?;
    let mut line = String::new();
    tokio::time::timeout(
        Duration::from_secs(10),
        BufReader::new(stdout).read_line(&mut line),
    )
    .await
    .context("hub did not start in 10 s")??;
    let addr = line
        .split_whitespace()
        .nth(4)
        .and_then(|a| a.parse().ok())
        .with_context(|| format!("unexpected hub banner {line:?}"))?;
    Ok(RunningHub {
        addr,
        child: Some(child),
    })
}

/// CPU time (user + system) of process `pid` so far, summed over its threads.
fn cpu_time(pid: u32) -> Option<Duration> {
    let tasks = std::fs::read_dir(format!("/proc/{pid}/task")).ok()?;
    let mut total = 0u64;
    for task in tasks.flatten() {
        let text = std::fs::read_to_string(task.path().join("schedstat")).ok()?;
        total += text.split_whitespace().next()?.parse::<u64>().ok()?;
    }
    Some(Duration::from_nanos(total))
}

#[derive(Default)]
struct ReceiverReport {
    received: u64,
    out_of_order: u64,
    latencies_us: Vec<u32>,
}

fn percentile(sorted: &[u32], p: f64) -> u32 {
    if sorted.is_empty() {
        return 0;
    }
    let rank = ((p / 100.0) * (sorted.len() - 1) as f64).round() as usize;
    sorted[rank.min(sorted.len() - 1)]
}

async fn run_hub_bench(args: HubBench) -> anyhow::Result<()> {
    if args.clients < 2 || args.senders == 0 || args.senders > args.clients {
        bail!("need at least 2 clients and 1..=clients senders");
    }
    let hub = match args.hub {
        Some(addr) => RunningHub { addr, child: None },
        None => start_hub(args.bitrate).await?,
    };
    let pid = hub.child.as_ref().and_then(|c| c.id());
    let url = format!("socketcand://{}/bench", hub.addr);
    let options = BusOptions {
        rx_queue: 1 << 16,
        ..Default::default()
    };
    let mut buses = Vec::new();
    for _ in 0..args.clients {
        buses.push(Bus::open_with(&url, options.clone()).await?);
    }
    // Let the hub's raw-mode hold pass before measuring.
    tokio::time::sleep(Duration::from_millis(200)).await;
    let start = Instant::now();
    let cpu_before = pid.and_then(cpu_time);
    let mut receivers = Vec::new();
    let mut senders = Vec::new();
    for (index, bus) in buses.into_iter().enumerate() {
        let (tx, mut rx) = bus.split();
        let expected =
            u64::from(args.frames) * (args.senders - usize::from(index < args.senders)) as u64;
        receivers.push(tokio::spawn(async move {
            let mut report = ReceiverReport::default();
            let mut last_seq = vec![None::<u32>; 256];
            while report.received < expected {
                let next = tokio::time::timeout(Duration::from_secs(10), rx.recv_frame()).await;
                let Ok(Some(frame)) = next else { break };
                let d = frame.data();
                let sender = (frame.id().as_raw() & 0xFF) as usize;
                let seq = u32::from_le_bytes([d[0], d[1], d[2], d[3]]);
                let sent_us = u32::from_le_bytes([d[4], d[5], d[6], d[7]]);
                let now_us = start.elapsed().as_micros() as u32;
                report.latencies_us.push(now_us.wrapping_sub(sent_us));
                if last_seq[sender].is_some_and(|l| seq != l + 1) {
                    report.out_of_order += 1;
                }
                last_seq[sender] = Some(seq);
                report.received += 1;
            }
            report
        }));
        if index < args.senders {
            let (frames, rate) = (args.frames, args.rate);
            senders.push(tokio::spawn(async move {
                let id = CanId::Standard(0x100 + index as u16);
                let mut tick = tokio::time::interval(Duration::from_millis(1));
                let per_tick = if rate == 0 {
                    u32::MAX
                } else {
                    rate.div_ceil(1000)
                };
                let mut seq = 0u32;
                while seq < frames {
                    if rate > 0 {
                        tick.tick().await;
                    }
                    for _ in 0..per_tick.min(frames - seq) {
                        let now_us = start.elapsed().as_micros() as u32;
                        let mut data = [0u8; 8];
                        data[..4].copy_from_slice(&seq.to_le_bytes());
                        data[4..].copy_from_slice(&now_us.to_le_bytes());
                        tx.send(Frame::new(id, &data)?).await?;
                        seq += 1;
                    }
                }
                anyhow::Ok(())
            }));
        }
    }
    for s in senders {
        s.await??;
    }
    let mut latencies = Vec::new();
    let (mut received, mut out_of_order) = (0u64, 0u64);
    for r in receivers {
        let report = r.await?;
        received += report.received;
        out_of_order += report.out_of_order;
        latencies.extend(report.latencies_us);
    }
    let elapsed = start.elapsed();
    let cpu = match (cpu_before, pid.and_then(cpu_time)) {
        (Some(a), Some(b)) => Some(b.saturating_sub(a)),
        _ => None,
    };
    latencies.sort_unstable();
    let sent = u64::from(args.frames) * args.senders as u64;
    let expected: u64 = sent * (args.clients as u64 - 1);
    println!(
        "hub bench: {} clients, {} sender(s), {} frames each, rate {}",
        args.clients,
        args.senders,
        args.frames,
        if args.rate == 0 {
            "flood".to_owned()
        } else {
            format!("{}/s", args.rate)
        }
    );
    println!(
        "  sent {sent} frames, delivered {received}/{expected} ({} lost, {out_of_order} out of order) in {:.3} s",
        expected.saturating_sub(received),
        elapsed.as_secs_f64()
    );
    println!(
        "  throughput: {:.0} frames/s sent, {:.0} frames/s delivered",
        sent as f64 / elapsed.as_secs_f64(),
        received as f64 / elapsed.as_secs_f64()
    );
    println!(
        "  latency: p50 {} us, p99 {} us, max {} us",
        percentile(&latencies, 50.0),
        percentile(&latencies, 99.0),
        latencies.last().copied().unwrap_or(0)
    );
    match cpu {
        Some(cpu) => println!(
            "  hub CPU: {:.3} s = {:.2} us per frame sent, {:.2} us per frame delivered",
            cpu.as_secs_f64(),
            cpu.as_secs_f64() * 1e6 / sent as f64,
            cpu.as_secs_f64() * 1e6 / received.max(1) as f64
        ),
        None => println!("  hub CPU: not measured (external hub or no /proc)"),
    }
    drop(hub);
    if received < expected {
        bail!("{} frames lost", expected - received);
    }
    Ok(())
}

/// Run a benchmark.
pub async fn run(args: BenchArgs) -> anyhow::Result<()> {
    match args.what {
        BenchKind::Hub(h) => run_hub_bench(h).await,
    }
}
