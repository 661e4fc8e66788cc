//! The bus benchmarks: the hub (frames/s, latency and CPU per frame, measured end to end), SDO
//! transfers (canlift's client and python-canopen's on one server) and a `LocalNode` (change →
//! TPDO latency, PDO rates, SYNC jitter, idle CPU).
//!
//! The hub runs as a separate process (`canlift hub`, or one given with `--hub`), so its CPU
//! time can be read from `/proc` apart from the clients'. Clients are canlift `socketcand://`
//! endpoints in this process. Every frame carries its sequence number and send time, so the
//! receivers measure one-way latency and check order and loss.

use std::net::SocketAddr;
use std::process::Stdio;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use canbus::BusOptions;
use canbus::{Bus, CanId, Frame};
use tokio::io::{AsyncBufReadExt, BufReader};

use crate::process::cpu_time;

#[derive(Debug, Clone, clap::Args)]
pub(crate) struct NodeBench {
    /// Changes timed for the change→TPDO latency.
    #[arg(long, default_value_t = 2000)]
    changes: u32,
    /// Seconds of PDO traffic for the frames/s figures.
    #[arg(long, default_value_t = 2)]
    seconds: u64,
    /// SYNCs measured at a 1 ms period.
    #[arg(long, default_value_t = 2000)]
    syncs: u32,
    /// Seconds the node idles for the CPU figure (0 skips it).
    #[arg(long, default_value_t = 60)]
    idle_seconds: u64,
}

#[derive(Debug, Clone, clap::Args)]
pub(crate) struct SdoBench {
    /// Expedited reads to time.
    #[arg(long, default_value_t = 2000)]
    reads: u32,
    /// Bytes per segmented/block transfer.
    #[arg(long, default_value_t = 65536)]
    size: usize,
    /// Start the hub with this --bitrate (then only block transfers are timed, against the
    /// bus ceiling).
    #[arg(long)]
    bitrate: Option<u32>,
    /// Python with python-canopen for the comparison [default: $CANLIFT_PYTHON or .venv/bin/python].
    #[arg(long)]
    python: Option<std::path::PathBuf>,
}

#[derive(Debug, Clone, clap::Args)]
pub(crate) struct HubBench {
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
    let exe = crate::canlift()?;
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

/// Percentiles of durations in µs.
fn micros(sorted: &[Duration], p: f64) -> f64 {
    if sorted.is_empty() {
        return 0.0;
    }
    let rank = ((p / 100.0) * (sorted.len() - 1) as f64).round() as usize;
    sorted[rank.min(sorted.len() - 1)].as_secs_f64() * 1e6
}

/// A started, operational node with TPDO1 = 0x2000 and RPDO1 = 0x2100 (both event-driven), and
/// a counter of stored RPDO values.
async fn pdo_node(
    url: &str,
) -> anyhow::Result<(
    canopen::node::LocalNode,
    std::sync::Arc<std::sync::atomic::AtomicU64>,
)> {
    use canopen::nmt::{NmtCommand, NmtState};
    use canopen::node::{LocalNode, NodeConfig, PdoSetup};
    use canopen::od::{Access, Object, ObjectDictionary, Variable};
    use canopen::types::DataType;

    let mut od = ObjectDictionary::new();
    od.insert(Object::var(
        0x2000,
        Variable::new("Counter", DataType::Unsigned32, Access::Rw).mappable(),
    ));
    od.insert(Object::var(
        0x2100,
        Variable::new("Setpoint", DataType::Unsigned32, Access::Rw).mappable(),
    ));
    let updates = std::sync::Arc::new(std::sync::atomic::AtomicU64::new(0));
    {
        let updates = updates.clone();
        od.watch(std::sync::Arc::new(move |index, _| {
            if index == 0x2100 {
                updates.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
        }));
    }
    let node = LocalNode::start(Bus::open(url).await?, od, NodeConfig::new(5));
    node.wait_for_state(NmtState::PreOperational).await;
    let setup = |transmit, cob_id, object| PdoSetup {
        transmit,
        number: 1,
        cob_id,
        objects: vec![(object, 0)],
        transmission_type: 254,
        inhibit_100us: 0,
        event_ms: 0,
    };
    node.configure_pdo(&setup(true, 0x185, 0x2000))
        .map_err(|c| anyhow::anyhow!("TPDO: {c}"))?;
    node.configure_pdo(&setup(false, 0x205, 0x2100))
        .map_err(|c| anyhow::anyhow!("RPDO: {c}"))?;
    node.nmt(NmtCommand::Start);
    node.wait_for_state(NmtState::Operational).await;
    Ok((node, updates))
}

pub(crate) async fn run_node_bench(args: NodeBench) -> anyhow::Result<()> {
    use canopen::types::Value;

    let hub = start_hub(None).await?;
    let url = format!("socketcand://{}/node", hub.addr);
    let (node, _) = pdo_node(&url).await?;
    let options = BusOptions {
        rx_queue: 1 << 20,
        ..Default::default()
    };
    let mut peer = Bus::open_with(&url, options.clone()).await?;
    peer.receiver.set_filters(&[
        canbus::Filter::standard(0x185, 0x7FF),
        canbus::Filter::standard(0x080, 0x7FF),
    ]);
    tokio::time::sleep(Duration::from_millis(200)).await;
    while peer.receiver.try_recv().is_some() {}
    println!("node bench: LocalNode (node 5) and a peer through canlift hub");

    // 1. Change → TPDO latency, one change at a time.
    let mut latencies = Vec::with_capacity(args.changes as usize);
    for i in 1..=args.changes {
        let start = Instant::now();
        node.set_value(0x2000, 0, &Value::Uint(i.into()))
            .map_err(|c| anyhow::anyhow!("{c}"))?;
        loop {
            let f = tokio::time::timeout(Duration::from_secs(2), peer.receiver.recv_frame())
                .await
                .context("TPDO did not arrive")?
                .context("bus closed")?;
            if f.data() == i.to_le_bytes() {
                break;
            }
        }
        latencies.push(start.elapsed());
    }
    latencies.sort_unstable();
    println!(
        "  OD change -> TPDO received: p50 {:.0} us, p99 {:.0} us ({} changes)",
        micros(&latencies, 50.0),
        micros(&latencies, 99.0),
        args.changes
    );

    // 2./3. What the node itself produces and consumes, on the in-process bus (the hub's own
    // capacity is `bench hub`; through it a flood makes slow readers be dropped by design).
    let mem_url = format!("mem://bench-node-{}", std::process::id());
    let (mem_node, updates) = pdo_node(&mem_url).await?;
    let mut mem_peer = Bus::open_with(&mem_url, options).await?;
    mem_peer
        .receiver
        .set_filters(&[canbus::Filter::standard(0x185, 0x7FF)]);
    let until = Instant::now() + Duration::from_secs(args.seconds);
    let counter = tokio::spawn(async move {
        let (mut frames, mut lost) = (0u64, 0u64);
        while let Ok(Some(event)) =
            tokio::time::timeout(Duration::from_millis(500), mem_peer.recv()).await
        {
            match event {
                canbus::BusEvent::Frame(_) => frames += 1,
                canbus::BusEvent::Overrun { dropped } => lost += dropped,
                _ => {}
            }
        }
        (frames, lost)
    });
    let mut value = 1_000_000u32;
    let started = Instant::now();
    while Instant::now() < until {
        for _ in 0..16 {
            value += 1;
            mem_node
                .set_value(0x2000, 0, &Value::Uint(value.into()))
                .map_err(|c| anyhow::anyhow!("{c}"))?;
        }
        tokio::task::yield_now().await;
    }
    let produce_time = started.elapsed().as_secs_f64();
    let (produced, lost) = counter.await?;
    println!(
        "  TPDOs produced (in-process bus): {:.0} frames/s ({} changes; changes within one turn of the node share a TPDO; {lost} lost by the reader)",
        (produced + lost) as f64 / produce_time,
        value - 1_000_000,
    );
    // Closed loop: a batch of RPDOs, then wait until the node has stored every one, so the
    // figure is the node's sustainable rate, not how fast a queue overflows.
    let sender = Bus::open(&mem_url).await?;
    let started = Instant::now();
    let mut sent = 0u64;
    let base = updates.load(std::sync::atomic::Ordering::Relaxed);
    while started.elapsed() < Duration::from_secs(args.seconds) {
        for _ in 0..1024 {
            sent += 1;
            sender
                .send(Frame::standard(0x205, &(sent as u32).to_le_bytes())?)
                .await?;
        }
        let deadline = Instant::now() + Duration::from_secs(2);
        while updates.load(std::sync::atomic::Ordering::Relaxed) - base < sent {
            anyhow::ensure!(Instant::now() < deadline, "RPDOs were lost");
            tokio::task::yield_now().await;
        }
    }
    println!(
        "  RPDOs consumed (in-process bus): {:.0} frames/s stored into the dictionary ({sent} frames, none lost)",
        sent as f64 / started.elapsed().as_secs_f64()
    );
    mem_node.stop().await;

    // 4. SYNC producer jitter at 1 ms.
    let sdo = canopen::sdo::clients::SdoClients::new(Bus::open(&url).await?, Default::default());
    sdo.write(5, 0x1006, 0, 1000u32).await?;
    sdo.write(5, 0x1005, 0, 0x4000_0080u32).await?;
    while peer.receiver.try_recv().is_some() {}
    let mut last = None;
    let mut jitter = Vec::with_capacity(args.syncs as usize);
    let mut periods = Vec::with_capacity(args.syncs as usize);
    while jitter.len() < args.syncs as usize {
        let f = tokio::time::timeout(Duration::from_secs(2), peer.receiver.recv_frame())
            .await
            .context("SYNC did not arrive")?
            .context("bus closed")?;
        if f.id() != CanId::Standard(0x80) {
            continue;
        }
        let now = Instant::now();
        if let Some(prev) = last {
            let period: Duration = now - prev;
            periods.push(period);
            jitter.push(if period > Duration::from_millis(1) {
                period - Duration::from_millis(1)
            } else {
                Duration::from_millis(1) - period
            });
        }
        last = Some(now);
    }
    sdo.write(5, 0x1005, 0, 0x80u32).await?;
    let mean = periods.iter().sum::<Duration>() / periods.len().max(1) as u32;
    jitter.sort_unstable();
    println!(
        "  SYNC at 1 ms (as received through the hub): mean period {:.1} us, jitter p50 {:.0} us, p99 {:.0} us",
        mean.as_secs_f64() * 1e6,
        micros(&jitter, 50.0),
        micros(&jitter, 99.0)
    );

    // 5. Idle CPU: heartbeat at 1 s, nothing else.
    if args.idle_seconds > 0 {
        sdo.write(5, 0x1017, 0, 1000u16).await?;
        tokio::time::sleep(Duration::from_millis(200)).await;
        let own = std::process::id();
        let before = cpu_time(own);
        tokio::time::sleep(Duration::from_secs(args.idle_seconds)).await;
        match (before, cpu_time(own)) {
            (Some(a), Some(b)) => println!(
                "  idle node (heartbeat 1 s, bus client, runtime) over {} s: {:.1} ms CPU",
                args.idle_seconds,
                (b.saturating_sub(a)).as_secs_f64() * 1e3
            ),
            _ => println!("  idle CPU: not measured (no /proc)"),
        }
    }
    node.stop().await;
    drop(hub);
    Ok(())
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

pub(crate) async fn run_hub_bench(args: HubBench) -> anyhow::Result<()> {
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

/// The time the data segments of a block transfer of `data` occupy a bus at `bitrate`: the
/// ceiling no block transfer can beat.
fn block_ceiling(data: &[u8], bitrate: u32) -> Duration {
    data.chunks(7)
        .enumerate()
        .map(|(i, chunk)| {
            let mut p = [0u8; 8];
            p[0] = (i % 127 + 1) as u8;
            p[1..1 + chunk.len()].copy_from_slice(chunk);
            let frame = Frame::new(CanId::Standard(0x585), &p).unwrap_or_else(|_| unreachable!());
            canbus::wire::frame_duration(&frame, bitrate)
        })
        .sum()
}

fn kib_s(bytes: usize, elapsed: Duration) -> f64 {
    bytes as f64 / 1024.0 / elapsed.as_secs_f64()
}

pub(crate) async fn run_sdo_bench(args: SdoBench) -> anyhow::Result<()> {
    use canopen::od::{Access, Object, ObjectDictionary, Variable};
    use canopen::sdo::client::{ClientConfig, Transfer};
    use canopen::sdo::clients::{SdoClients, TransferOptions};
    use canopen::sdo::serve::serve_sdo;
    use canopen::sdo::server::ServerConfig;
    use canopen::types::{DataType, Value};

    let hub = start_hub(args.bitrate).await?;
    let url = format!("socketcand://{}/sdo", hub.addr);
    let mut od = ObjectDictionary::new();
    od.insert(Object::var(
        0x1000,
        Variable::new("Device type", DataType::Unsigned32, Access::Ro)
            .with_value(Value::Uint(0x0001_01A1)),
    ));
    od.insert(Object::var(
        0x2000,
        Variable::new("Blob", DataType::Domain, Access::Rw),
    ));
    let od = std::sync::Arc::new(std::sync::Mutex::new(od));
    let server = serve_sdo(Bus::open(&url).await?, od, 5, ServerConfig::default());
    let config = ClientConfig {
        timeout: Duration::from_secs(5),
        ..ClientConfig::default()
    };
    let sdo = SdoClients::new(Bus::open(&url).await?, config);
    tokio::time::sleep(Duration::from_millis(200)).await;
    let data: Vec<u8> = (0..args.size).map(|i| (i * 131 + 7) as u8).collect();
    let timed = |how: Transfer, download: bool| {
        let (sdo, data) = (sdo.clone(), data.clone());
        async move {
            let options = TransferOptions {
                how,
                ..TransferOptions::default()
            };
            let start = Instant::now();
            if download {
                sdo.write_with(5, 0x2000, 0, data, options).await?;
            } else {
                let back = sdo.read_with(5, 0x2000, 0, options).await?;
                anyhow::ensure!(back == data, "uploaded data differs");
            }
            anyhow::Ok(start.elapsed())
        }
    };
    println!(
        "SDO bench: node 5 served by canlift through canlift hub{}",
        match args.bitrate {
            Some(b) => format!(" at {b} bit/s"),
            None => " (no bit-rate limit)".to_owned(),
        }
    );
    if let Some(bitrate) = args.bitrate {
        let ceiling = block_ceiling(&data, bitrate);
        let ceiling_rate = kib_s(args.size, ceiling);
        println!(
            "  ceiling for {} bytes of block data at {bitrate} bit/s: {ceiling_rate:.2} KiB/s",
            args.size
        );
        for (name, download) in [("block download", true), ("block upload", false)] {
            let t = timed(Transfer::Block, download).await?;
            let rate = kib_s(args.size, t);
            println!(
                "  {name:<16} {rate:8.2} KiB/s = {:.1} % of the ceiling",
                rate / ceiling_rate * 100.0
            );
        }
        server.abort();
        return Ok(());
    }
    let start = Instant::now();
    for _ in 0..args.reads {
        sdo.read_raw(5, 0x1000, 0).await?;
    }
    let reads = f64::from(args.reads) / start.elapsed().as_secs_f64();
    let mut ours = vec![("expedited_reads_per_s", reads)];
    for (key, how, download) in [
        ("segmented_download_kib_s", Transfer::Segmented, true),
        ("segmented_upload_kib_s", Transfer::Segmented, false),
        ("block_download_kib_s", Transfer::Block, true),
        ("block_upload_kib_s", Transfer::Block, false),
    ] {
        ours.push((key, kib_s(args.size, timed(how, download).await?)));
    }
    let python = args
        .python
        .or_else(|| std::env::var_os("CANLIFT_PYTHON").map(Into::into))
        .unwrap_or_else(|| ".venv/bin/python".into());
    let theirs = tokio::process::Command::new(&python)
        .arg("tests/interop/bench_sdo_python.py")
        .args([
            hub.addr.ip().to_string(),
            hub.addr.port().to_string(),
            "sdo".into(),
            "5".into(),
        ])
        .args([args.reads.to_string(), args.size.to_string()])
        .output()
        .await;
    let theirs: Option<std::collections::HashMap<String, f64>> = match theirs {
        Ok(out) if out.status.success() => {
            parse_json_numbers(&String::from_utf8_lossy(&out.stdout))
        }
        Ok(out) => {
            println!(
                "  python-canopen comparison failed: {}",
                String::from_utf8_lossy(&out.stderr)
                    .lines()
                    .last()
                    .unwrap_or("")
            );
            None
        }
        Err(e) => {
            println!("  python-canopen comparison skipped ({}: {e}); run scripts/test once to create .venv", python.display());
            None
        }
    };
    println!(
        "  {:<26} {:>12} {:>16} {:>7}",
        "", "canlift", "python-canopen", "ratio"
    );
    for (key, value) in ours {
        match theirs.as_ref().and_then(|t| t.get(key)) {
            Some(p) => println!("  {key:<26} {value:>12.1} {p:>16.1} {:>6.1}x", value / p),
            None => println!("  {key:<26} {value:>12.1}"),
        }
    }
    server.abort();
    Ok(())
}

/// The numbers of a flat JSON object (the Python side prints one line of them).
fn parse_json_numbers(text: &str) -> Option<std::collections::HashMap<String, f64>> {
    let body = text.trim().strip_prefix('{')?.strip_suffix('}')?;
    body.split(',')
        .map(|pair| {
            let (k, v) = pair.split_once(':')?;
            Some((
                k.trim().trim_matches('"').to_owned(),
                v.trim().parse().ok()?,
            ))
        })
        .collect()
}
