//! `canlift-bench gateway`: the elevator gateway measured from a portal's seat — request latency
//! and rate for naked, stripped and full gets (on a local dictionary, the same with the
//! controller described by an EDS and a vendor file, and by SDO through the hub to the simulated
//! lift), the cost of one metadata lookup per source, notifications per second, the resident memory of a gateway process
//! idle and with many subscriptions, and the size of the stripped binary.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use futures_util::{SinkExt, StreamExt};
use gateway::config::{Config, NodeSection, SdoChannel};
use gateway::metadata::BusMetadata;
use gateway::Gateway;
use lift417::catalog::{Catalog, Device};
use lift417::sim::{export_eds, SimConfig, Simulator};
use nxg::gateway::{Metadata, Target};
use serde_json::{json, Value};
use tokio::net::{TcpListener, TcpStream};
use tokio_rustls::server::TlsStream;
use tokio_tungstenite::tungstenite::handshake::server::{Request, Response};
use tokio_tungstenite::tungstenite::http::HeaderValue;
use tokio_tungstenite::tungstenite::Message;
use tokio_tungstenite::WebSocketStream;

use cloud::devpki::{self, DevPki};

use crate::gets::get;
use crate::process::{lone_gateway, memory_kib, mib, percentile, Daemon};

/// Arguments of `canlift-bench gateway`.
#[derive(Debug, Clone, clap::Args)]
pub struct GatewayBench {
    /// Requests per form for the latency and rate figures.
    #[arg(long, default_value_t = 2000)]
    requests: usize,
    /// Requests kept outstanding for the rate figures.
    #[arg(long, default_value_t = 16)]
    window: usize,
    /// Seconds of value changes for the notification figure.
    #[arg(long, default_value_t = 2)]
    seconds: u64,
    /// Subscriptions for the memory figure.
    #[arg(long, default_value_t = 1000)]
    subscriptions: usize,
    /// The canlift binary whose `gateway` is measured for memory and size — e.g. a
    /// `--no-default-features` build, as a gateway device would run; default: this one.
    #[arg(long)]
    exe: Option<PathBuf>,
    /// Only the gateway's CPU per request (its own process, read from /proc).
    #[arg(long)]
    cpu_only: bool,
    /// SDO channels to the simulated controller for the CPU figure's second bus-node run (its
    /// default channel and up to 7 further ones; 1: no second run; 0: the local dictionary
    /// alone).
    #[arg(long, default_value_t = 4, value_parser = clap::value_parser!(u8).range(0..=8))]
    sdo_channels: u8,
    /// Only the memory of a `canlift gateway` process, idle and with `--subscriptions`.
    #[arg(long)]
    memory_only: bool,
    /// Only the growth curve of request latency against subscriptions held (1…10,000), as
    /// CSV and SVG into this directory.
    #[arg(long)]
    curves: Option<PathBuf>,
}

impl GatewayBench {
    fn exe(&self) -> anyhow::Result<PathBuf> {
        Ok(match &self.exe {
            Some(e) => e.clone(),
            None => crate::canlift()?,
        })
    }
}

pub(crate) type Ws = WebSocketStream<TlsStream<TcpStream>>;

/// A stand-in portal: TLS WebSocket server that accepts one gateway's CONNECT, so requests can
/// be timed at the gateway's own door.
pub(crate) struct Portal {
    listener: TcpListener,
    acceptor: tokio_rustls::TlsAcceptor,
}

impl Portal {
    pub(crate) async fn start(pki: &DevPki) -> anyhow::Result<Portal> {
        let config = tls::server_config(&pki.cert, &pki.key, None)?;
        Ok(Portal {
            listener: TcpListener::bind("127.0.0.1:0").await?,
            acceptor: tokio_rustls::TlsAcceptor::from(Arc::new(config)),
        })
    }

    pub(crate) fn url(&self) -> anyhow::Result<String> {
        Ok(format!("wss://localhost:{}/ws", self.addr()?.port()))
    }

    /// Where it listens.
    pub(crate) fn addr(&self) -> anyhow::Result<std::net::SocketAddr> {
        Ok(self.listener.local_addr()?)
    }

    /// Accept a gateway and answer its CONNECT.
    pub(crate) async fn accept(&self) -> anyhow::Result<Ws> {
        let (tcp, _) = tokio::time::timeout(Duration::from_secs(20), self.listener.accept())
            .await
            .context("no gateway connected")??;
        let _ = tcp.set_nodelay(true);
        let tls = self.acceptor.accept(tcp).await?;
        #[allow(clippy::result_large_err)] // the callback's error type is tungstenite's
        let select = |_: &Request, mut resp: Response| {
            resp.headers_mut()
                .insert("Sec-WebSocket-Protocol", HeaderValue::from_static("cloud"));
            Ok(resp)
        };
        let mut ws = tokio_tungstenite::accept_hdr_async(tls, select).await?;
        let connect = recv(&mut ws).await?;
        // As a portal does: the lower of both sides' API versions.
        let offered = connect["params"]["identity"]["api"].as_u64().unwrap_or(1);
        let api = offered.min(u64::from(nxg::msg::API));
        let answer =
            json!({"jsonrpc": "2.0", "id": connect["id"], "result": "CONNACK", "api": api});
        ws.send(Message::Text(answer.to_string().into())).await?;
        Ok(ws)
    }
}

async fn recv(ws: &mut Ws) -> anyhow::Result<Value> {
    loop {
        match tokio::time::timeout(Duration::from_secs(20), ws.next()).await {
            Ok(Some(Ok(Message::Text(t)))) => return Ok(serde_json::from_str(t.as_str())?),
            Ok(Some(Ok(Message::Ping(_) | Message::Pong(_)))) => continue,
            Ok(other) => bail!("the gateway sent {other:?}"),
            Err(_) => bail!("no message from the gateway in 20 s"),
        }
    }
}

fn config(url: &str, pki: &DevPki, bus: &str, state: &Path) -> Config {
    let mut c = Config::default();
    c.identity.sernum = "bench".into();
    c.identity.vendorid = 1050;
    c.identity.productcode = 4096;
    c.cloud.url = url.into();
    c.cloud.ca_file = Some(pki.ca.clone());
    c.state.dir = state.to_path_buf();
    c.bus.url = bus.into();
    c.limits.max_in_flight = 64;
    c.limits.max_subscriptions = 4096;
    c
}

/// `n` gets of 0x652001 in `form` one after another; their round-trip times, sorted.
pub(crate) async fn sequential_gets(
    ws: &mut Ws,
    form: &str,
    n: usize,
) -> anyhow::Result<Vec<Duration>> {
    let mut times = Vec::with_capacity(n);
    for id in 0..n {
        let started = Instant::now();
        ws.send(Message::Text(get(id, "0x652001", form).into()))
            .await?;
        let answer = recv(ws).await?;
        if answer.get("result").is_none() {
            bail!("{form} get failed: {answer}");
        }
        times.push(started.elapsed());
    }
    times.sort();
    Ok(times)
}

/// How requests come while a window is kept outstanding.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Refill {
    /// A new request as each answer is read: the requests trickle in, one per answer.
    Trickle,
    /// The answers that came together are read first, then the window is topped up in one
    /// write: requests come in bursts.
    Bursts,
}

/// `n` gets of 0x652001 in `form` with `window` of them outstanding, refilled as `refill`
/// says; an error answer ends it, notifications in between are passed over.
async fn windowed_gets(
    ws: &mut Ws,
    form: &str,
    n: usize,
    window: usize,
    refill: Refill,
) -> anyhow::Result<()> {
    let (mut sent, mut done) = (0, 0);
    while done < n {
        while sent < n && sent - done < window {
            ws.feed(Message::Text(get(sent, "0x652001", form).into()))
                .await?;
            sent += 1;
        }
        ws.flush().await?;
        let mut answer = Some(recv(ws).await?);
        while let Some(a) = answer {
            if a.get("error").is_some() {
                bail!("{form} get failed: {a}");
            }
            if a.get("result").is_some() {
                done += 1;
            }
            answer = match refill {
                Refill::Trickle => None,
                Refill::Bursts => futures_util::FutureExt::now_or_never(recv(ws)).transpose()?,
            };
        }
    }
    Ok(())
}

/// Sequential requests (latency), then `window` outstanding (rate), for each form.
async fn requests(ws: &mut Ws, what: &str, args: &GatewayBench) -> anyhow::Result<()> {
    for form in ["naked", "stripped", "full"] {
        let times = sequential_gets(ws, form, args.requests).await?;
        let started = Instant::now();
        windowed_gets(ws, form, args.requests, args.window, Refill::Trickle).await?;
        let rate = args.requests as f64 / started.elapsed().as_secs_f64();
        println!(
            "{what:<22} {form:<9} p50 {:>8.0} µs   p99 {:>8.0} µs   {rate:>8.0} requests/s (window {})",
            percentile(&times, 50.0),
            percentile(&times, 99.0),
            args.window
        );
    }
    Ok(())
}

async fn notifications(
    ws: &mut Ws,
    od: canopen::od::SharedDictionary,
    seconds: u64,
) -> anyhow::Result<()> {
    let reg = r#"{"jsonrpc":"2.0","id":"r","method":"reg_canopen_object","params":{"mplex":["0x652001"],"inhibit":0,"threshold":0}}"#;
    ws.send(Message::Text(reg.into())).await?;
    let period = Duration::from_secs(seconds.max(1));
    let changer = tokio::task::spawn_blocking(move || {
        let started = Instant::now();
        let mut n: u64 = 0;
        while started.elapsed() < period {
            n += 1;
            let value = canopen::types::Value::Uint(n);
            let _ = od.lock().map(|mut od| od.set_value(0x6520, 1, &value));
            if n.is_multiple_of(64) {
                std::thread::yield_now();
            }
        }
        n
    });
    let started = Instant::now();
    let mut pushed = 0u64;
    while started.elapsed() < period {
        if let Ok(Ok(v)) = tokio::time::timeout(Duration::from_millis(200), recv(ws)).await {
            if v["method"] == "canopen_object" {
                pushed += 1;
            }
        }
    }
    let changes = changer.await?;
    let secs = period.as_secs_f64();
    println!(
        "{:<22} {:.0} notifications/s while the controller changed the value {:.0} times/s (changes coalesce; the latest value is always sent)",
        "local dictionary",
        pushed as f64 / secs,
        changes as f64 / secs
    );
    Ok(())
}

/// The simulated controller's exported EDS and a vendor metadata file naming 6520h sub 1, as
/// `[[bus.nodes]]` for the controller.
fn described_controller(dir: &Path) -> anyhow::Result<NodeSection> {
    let eds = dir.join("controller.eds");
    std::fs::write(&eds, export_eds(&SimConfig::default(), Device::Controller)?)?;
    let metadata = dir.join("controller-nxg.toml");
    std::fs::write(
        &metadata,
        r#"languages = ["en", "de"]

[[object]]
index = 0x6520
code = "array"
name = { en = "Counters", de = "Zähler" }
type = 7
form = 10
access = "ro"
len = 2
item = { en = "Counter {i}", de = "Zähler {i}" }
sub = [{ sub = 1, name = { en = "Trips", de = "Fahrten" } }]
"#,
    )?;
    Ok(NodeSection {
        metadata: Some(metadata),
        ..NodeSection::with_eds(1, eds)
    })
}

/// The cost of describing 6520h sub 1 (what a full get looks up) by each source of metadata,
/// without the connection around it.
fn metadata_lookups(pki: &DevPki, described: &NodeSection) -> anyhow::Result<()> {
    let controller = Target { net: 1, node: 1 };
    let mut c = config("wss://unused/ws", pki, "mem://unused", Path::new("unused"));
    let catalog_only = BusMetadata::load(&c)?;
    c.bus.nodes = vec![NodeSection {
        metadata: None,
        ..described.clone()
    }];
    let with_eds = BusMetadata::load(&c)?;
    c.bus.nodes = vec![described.clone()];
    let with_vendor = BusMetadata::load(&c)?;
    const N: u32 = 200_000;
    for (what, m) in [
        ("catalog", &catalog_only),
        ("EDS + catalog", &with_eds),
        ("EDS + vendor file", &with_vendor),
    ] {
        let started = Instant::now();
        for _ in 0..N {
            std::hint::black_box(m.lookup(controller, std::hint::black_box(0x6520), 1));
        }
        let per = started.elapsed() / N;
        println!(
            "metadata lookup        {what:<18} {:>6} ns per description",
            per.as_nanos()
        );
    }
    Ok(())
}

/// A flood of EMCY frames on the gateway's bus (as fast as the in-process bus takes them, from
/// all 127 node-IDs) while a portal registered for EMCY events reads them: the events the
/// gateway forwards per second, and the growth of this process's memory (the gateway keeps at
/// most `max_queued_events` waiting; the rest of the flood is dropped and counted).
async fn emcy_flood(args: &GatewayBench, pki: &DevPki, dir: &Path) -> anyhow::Result<()> {
    let bus = "mem://bench-emcy-flood";
    let portal = Portal::start(pki).await?;
    let gateway = Gateway::bus_node(config(&portal.url()?, pki, bus, &dir.join("emcy"))).await?;
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let task = tokio::spawn(gateway.run(stopped));
    let mut ws = portal.accept().await?;
    let reg =
        r#"{"jsonrpc":"2.0","id":"e","method":"reg_canopen_event","params":{"events":["emcy"]}}"#;
    ws.send(Message::Text(reg.into())).await?;
    while recv(&mut ws).await?.get("result").is_none() {}
    let before = memory_kib(std::process::id()).map_or(0, |m| m[0]);
    let period = Duration::from_secs(args.seconds.max(1));
    let flood = canbus::Bus::open(bus).await?;
    let sender = tokio::spawn(async move {
        let started = Instant::now();
        let mut sent: u64 = 0;
        while started.elapsed() < period {
            let node = (sent % 127) as u16 + 1;
            let data = [0x01, 0xFF, 0x21, 0, 0, 0, 0, (sent & 0xFF) as u8];
            if let Ok(frame) = canbus::Frame::standard(0x080 + node, &data) {
                let _ = flood.send(frame).await;
            }
            sent += 1;
            if sent.is_multiple_of(64) {
                tokio::task::yield_now().await;
            }
        }
        sent
    });
    let started = Instant::now();
    let mut forwarded = 0u64;
    let mut peak = before;
    while started.elapsed() < period + Duration::from_millis(500) {
        match tokio::time::timeout(Duration::from_millis(200), recv(&mut ws)).await {
            Ok(Ok(v)) if v["method"] == "canopen_event" => forwarded += 1,
            Ok(Ok(_)) | Err(_) => {}
            Ok(Err(e)) => return Err(e),
        }
        if forwarded.is_multiple_of(1024) {
            peak = peak.max(memory_kib(std::process::id()).map_or(0, |m| m[0]));
        }
    }
    let sent = sender.await?;
    let secs = period.as_secs_f64();
    println!(
        "{:<22} {:.0} EMCY frames/s on the bus, {:.0} events/s forwarded ({:.1} %), RSS +{:.1} MiB at most",
        "EMCY flood",
        sent as f64 / secs,
        forwarded as f64 / secs,
        100.0 * forwarded as f64 / sent.max(1) as f64,
        mib(peak.saturating_sub(before))
    );
    let _ = stop.send(true);
    let _ = task.await;
    Ok(())
}

/// Readable entries of the simulated controller, for subscriptions.
fn subscribable(n: usize) -> Vec<String> {
    let mut out = Vec::new();
    for o in Catalog::builtin()
        .objects()
        .filter(|o| o.held_by(Device::Controller) && !o.per_floor())
    {
        for e in o.entries().filter(|e| e.sub > 0) {
            if e.description.access != nxg::meta::Access::Wo {
                out.push(
                    nxg::mplex::Mplex {
                        index: o.index(),
                        sub: e.sub,
                    }
                    .to_string(),
                );
            }
        }
    }
    out.truncate(n);
    out
}

/// The gateway's own CPU time per request, read from `/proc` while this process plays the
/// portal: an embedded-mode gateway on a local dictionary (`canlift loadgen --gateways 1`: the
/// real gateway in a process of its own) and `canlift gateway` in bus-node mode, reading the
/// simulator by SDO through the hub. Naked gets of 0x652001, every answer checked; one at a time,
/// then `--window` outstanding. Then the least such a request can cost this machine
/// (`least::measure`), for scale.
async fn cpu_per_request(
    args: &GatewayBench,
    pki: &DevPki,
    hub: std::net::SocketAddr,
    dir: &Path,
) -> anyhow::Result<()> {
    let exe = args.exe()?;
    let bus = &bus_url(hub);
    // The controller's default SDO channel alone, then with the further ones the simulator
    // offers (docs/GATEWAY.md §Behaviour: a channel carries one transfer at a time).
    let mut modes = vec![("local dictionary".to_owned(), 0)];
    if args.sdo_channels > 0 {
        modes.push(("SDO via hub to sim".to_owned(), 1));
    }
    if args.sdo_channels > 1 {
        let n = usize::from(args.sdo_channels);
        modes.push((format!("SDO, {n} channels"), n));
    }
    for (mode, channels) in modes {
        let portal = Portal::start(pki).await?;
        let url = portal.url()?;
        let mut daemon = if channels == 0 {
            lone_gateway(&exe, &url, &pki.ca, "BENCH", 1, &dir.join("cpu-local"))?
        } else {
            let mut config = config(&url, pki, bus, &dir.join("cpu-bus"));
            if channels > 1 {
                let default = SdoChannel {
                    request: 0x601,
                    response: 0x581,
                };
                config.bus.nodes = vec![NodeSection {
                    sdo_channels: std::iter::once(default)
                        .chain(sim_sdo_servers())
                        .take(channels)
                        .collect(),
                    ..NodeSection::new(1)
                }];
            }
            let path = dir.join("cpu-gateway.toml");
            std::fs::write(&path, toml::to_string_pretty(&config)?)?;
            Daemon::start(&exe, "gateway", &path, None)?
        };
        let mut ws = portal.accept().await?;
        // Warm up (first reads, allocations) and let the start settle.
        sequential_gets(&mut ws, "naked", 200).await?;
        tokio::time::sleep(Duration::from_millis(500)).await;
        // One at a time, then the window refilled both ways: what a request costs the gateway
        // depends on how many come per wake-up, which is the portal's doing.
        let runs = [
            (1, Refill::Trickle, ""),
            (args.window, Refill::Trickle, ", one per answer"),
            (args.window, Refill::Bursts, ", refilled in bursts"),
        ];
        for (window, refill, how) in runs {
            let before = crate::process::schedstat(daemon.pid);
            let started = Instant::now();
            windowed_gets(&mut ws, "naked", args.requests, window, refill).await?;
            let rate = args.requests as f64 / started.elapsed().as_secs_f64();
            let (cpu, slices) = crate::process::used_since(daemon.pid, before).unwrap_or_default();
            let per_request = |n: f64| n / args.requests as f64;
            // Each wake-up costs the same whatever it serves: requests per wake-up say
            // whether a change in CPU per request is the work's or the batching's.
            println!(
                "gateway CPU per request  {mode:<20} {window:>2} in flight{how}: {:.1} µs (the gateway process alone, {} naked gets; {rate:.0} requests/s; {:.2} wake-ups per request)",
                per_request(cpu.as_secs_f64() * 1e6),
                args.requests,
                per_request(slices as f64),
            );
        }
        daemon.stop(Duration::from_secs(5)).await;
    }
    if args.sdo_channels > 0 {
        let requests = args.requests;
        let least =
            tokio::task::spawn_blocking(move || crate::least::measure(hub, requests)).await??;
        println!(
            "the least a request on one SDO channel costs here: {:.1} µs CPU, {:.2} wake-ups (a thread writing the SDO request to the hub, blocking for the answer, writing 200 bytes to a socket: no TLS, JSON or runtime; {requests} requests)",
            least.cpu_us, least.wakeups,
        );
        let pki = pki.clone();
        let (sans_io, work) =
            tokio::task::spawn_blocking(move || crate::least::measure_sans_io(hub, requests, &pki))
                .await??;
        println!(
            "the same with the connector's own work, sans-IO, no runtime: {:.1} µs CPU, {:.2} wake-ups (TLS record and WebSocket frame opened, NXg session, SDO client, socketcand text, answer framed and sealed; {requests} requests); that work alone in a loop without sleeping: {work:.1} µs",
            sans_io.cpu_us, sans_io.wakeups,
        );
    }
    Ok(())
}

async fn memory(args: &GatewayBench, pki: &DevPki, bus: &str, dir: &Path) -> anyhow::Result<()> {
    let portal = Portal::start(pki).await?;
    let config = config(&portal.url()?, pki, bus, &dir.join("process"));
    let path = dir.join("gateway.toml");
    std::fs::write(&path, toml::to_string_pretty(&config)?)?;
    let mut daemon = Daemon::start(&args.exe()?, "gateway", &path, None)?;
    let pid = daemon.pid;
    let mut ws = portal.accept().await?;
    tokio::time::sleep(Duration::from_secs(2)).await;
    let idle = memory_kib(pid).unwrap_or_default();
    let mplexes = subscribable(args.subscriptions);
    for (i, chunk) in mplexes.chunks(100).enumerate() {
        let reg = json!({"jsonrpc": "2.0", "id": i, "method": "reg_canopen_object",
            "params": {"mplex": chunk, "inhibit": 1000, "threshold": 1}});
        ws.send(Message::Text(reg.to_string().into())).await?;
        loop {
            let v = recv(&mut ws).await?;
            if v["id"] == json!(i) {
                if v.get("error").is_some() {
                    bail!("registration failed: {v}");
                }
                break;
            }
        }
    }
    let settle = Instant::now();
    while settle.elapsed() < Duration::from_secs(3) {
        let _ = tokio::time::timeout(Duration::from_millis(100), recv(&mut ws)).await;
    }
    let subscribed = memory_kib(pid).unwrap_or_default();
    for (what, [rss, pss, anon]) in [("idle", idle), ("subscribed", subscribed)] {
        let label = if what == "idle" {
            "gateway idle".to_owned()
        } else {
            format!("gateway, {} subs", mplexes.len())
        };
        println!(
            "{label:<22} RSS {:.1} MiB   PSS {:.1} MiB   anonymous {:.1} MiB (goal: ≤ 8 MiB RSS with 1,000 subscriptions, device build)",
            mib(rss),
            mib(pss),
            mib(anon)
        );
    }
    daemon.stop(Duration::from_secs(5)).await;
    Ok(())
}

fn binary_size(exe: &Path, dir: &Path) -> anyhow::Result<()> {
    let copy: PathBuf = dir.join("canlift-stripped");
    std::fs::copy(exe, &copy)?;
    let stripped = std::process::Command::new("strip").arg(&copy).status();
    let size = std::fs::metadata(&copy)?.len();
    match stripped {
        Ok(s) if s.success() => println!(
            "{:<22} {:.1} MiB stripped ({})",
            "binary",
            size as f64 / (1024.0 * 1024.0),
            exe.display()
        ),
        _ => println!(
            "{:<22} {:.1} MiB (strip not available)",
            "binary",
            size as f64 / (1024.0 * 1024.0)
        ),
    }
    Ok(())
}

/// Run every gateway measurement.
pub async fn run(args: GatewayBench) -> anyhow::Result<()> {
    let dir = tempfile::Builder::new()
        .prefix("canlift-bench-gateway-")
        .tempdir()?;
    let pki = devpki::ensure(dir.path())?;
    let result = measure(&args, &pki, dir.path()).await;
    result
}

/// The further SDO server channels of the benchmark's simulated controller (1201h–1207h:
/// 6A1h/6C1h … 6A7h/6C7h).
fn sim_sdo_servers() -> impl Iterator<Item = SdoChannel> {
    (1..=7).map(|n| SdoChannel {
        request: 0x6A0 + n,
        response: 0x6C0 + n,
    })
}

/// The bus of the hub listening on `hub`.
fn bus_url(hub: std::net::SocketAddr) -> String {
    format!("socketcand://{hub}/can0")
}

/// A hub on a loopback port with the simulated lift on it; the bus URL.
async fn hub_with_simulator() -> anyhow::Result<(canbus::hub::HubHandle, String, Simulator)> {
    let hub = canbus::hub::Hub::bind(canbus::hub::HubConfig {
        listen: std::net::SocketAddr::from(([127, 0, 0, 1], 0)),
        ..canbus::hub::HubConfig::default()
    })
    .await?
    .spawn()?;
    let bus = bus_url(hub.local_addr());
    let sim = SimConfig {
        sdo_servers: sim_sdo_servers().map(|c| c.ids()).collect(),
        ..SimConfig::default()
    };
    let sim = Simulator::start(&bus, sim).await?;
    Ok((hub, bus, sim))
}

/// Request latency (naked gets, one at a time) of an embedded gateway on a local dictionary
/// of 8 lifts and 254 floors while it holds more and more subscriptions of objects that do not
/// change — the cost of holding them, not of pushing.
async fn subscriptions_curve(
    args: &GatewayBench,
    pki: &DevPki,
    dir: &Path,
    out: &Path,
) -> anyhow::Result<()> {
    let od = Catalog::builtin().dictionary(Device::Controller, 8, 254)?;
    let readable: Vec<String> = od
        .objects()
        .filter(|o| o.index != 0x6520)
        .flat_map(|o| {
            o.subs
                .iter()
                .filter(|(sub, v)| **sub > 0 && v.access.readable())
                .map(|(sub, _)| {
                    nxg::mplex::Mplex {
                        index: o.index,
                        sub: *sub,
                    }
                    .to_string()
                })
        })
        .collect();
    let portal = Portal::start(pki).await?;
    let mut c = config(&portal.url()?, pki, "mem://unused", &dir.join("curve"));
    c.limits.max_subscriptions = readable.len() + 1;
    let gateway = Gateway::embedded(c, Arc::new(Mutex::new(od)))?;
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let task = tokio::spawn(gateway.run(stopped));
    let mut ws = portal.accept().await?;
    let (mut p50, mut p99) = (Vec::new(), Vec::new());
    let mut held = 0;
    for target in [1, 10, 100, 1000, 2000, 5000, 10_000] {
        let target = target.min(readable.len());
        for (i, chunk) in readable[held..target].chunks(100).enumerate() {
            let reg = json!({"jsonrpc": "2.0", "id": format!("r{held}-{i}"), "method": "reg_canopen_object",
                "params": {"mplex": chunk, "inhibit": 0, "threshold": 0}});
            ws.send(Message::Text(reg.to_string().into())).await?;
            loop {
                let v = recv(&mut ws).await?;
                if v["id"] == json!(format!("r{held}-{i}")) {
                    if v.get("error").is_some() {
                        bail!("registration failed: {v}");
                    }
                    break;
                }
            }
        }
        held = target;
        // Each registration pushes its object's value once: let those pass.
        while let Ok(answer) = tokio::time::timeout(Duration::from_millis(500), recv(&mut ws)).await
        {
            answer?;
        }
        let times = sequential_gets(&mut ws, "naked", args.requests).await?;
        let (a, b) = (percentile(&times, 50.0), percentile(&times, 99.0));
        println!("gateway, {held:>5} subscriptions held: naked get p50 {a:.0} µs, p99 {b:.0} µs");
        p50.push((held as f64, a));
        p99.push((held as f64, b));
        if held == readable.len() {
            break;
        }
    }
    let _ = stop.send(true);
    let _ = task.await;
    crate::plot::Curve {
        name: "gateway-subscriptions",
        title: "Gateway request latency vs subscriptions held",
        x: "subscriptions held",
        y: "naked get round trip (µs)",
        series: vec![
            crate::plot::Series {
                name: "p50",
                points: p50,
            },
            crate::plot::Series {
                name: "p99",
                points: p99,
            },
        ],
    }
    .write(out)
}

async fn measure(args: &GatewayBench, pki: &DevPki, dir: &Path) -> anyhow::Result<()> {
    if let Some(out) = &args.curves {
        return subscriptions_curve(args, pki, dir, out).await;
    }
    if args.cpu_only || args.memory_only {
        let (hub, bus, sim) = hub_with_simulator().await?;
        let measured = if args.cpu_only {
            cpu_per_request(args, pki, hub.local_addr(), dir).await
        } else {
            memory(args, pki, &bus, dir).await
        };
        sim.stop().await;
        hub.shutdown().await;
        return measured;
    }
    // On a local dictionary (embedded mode).
    let portal = Portal::start(pki).await?;
    let od = Catalog::builtin().dictionary(Device::Controller, 1, 8)?;
    let od = Arc::new(Mutex::new(od));
    let gateway = Gateway::embedded(
        config(&portal.url()?, pki, "mem://unused", &dir.join("local")),
        od.clone(),
    )?;
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let task = tokio::spawn(gateway.run(stopped));
    let mut ws = portal.accept().await?;
    requests(&mut ws, "local dictionary", args).await?;
    notifications(&mut ws, od.clone(), args.seconds).await?;
    let _ = stop.send(true);
    let _ = task.await;
    // The same with the controller described by an EDS and a vendor metadata file.
    let described = described_controller(dir)?;
    let portal = Portal::start(pki).await?;
    let mut c = config(&portal.url()?, pki, "mem://unused", &dir.join("eds"));
    c.bus.nodes = vec![described.clone()];
    let gateway = Gateway::embedded(c, od)?;
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let task = tokio::spawn(gateway.run(stopped));
    let mut ws = portal.accept().await?;
    requests(&mut ws, "local + EDS + vendor", args).await?;
    let _ = stop.send(true);
    let _ = task.await;
    metadata_lookups(pki, &described)?;
    // By SDO through the hub to the simulated lift (bus-node mode).
    let (hub, bus, sim) = hub_with_simulator().await?;
    let portal = Portal::start(pki).await?;
    let gateway = Gateway::bus_node(config(&portal.url()?, pki, &bus, &dir.join("bus"))).await?;
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let task = tokio::spawn(gateway.run(stopped));
    let mut ws = portal.accept().await?;
    requests(&mut ws, "SDO via hub to sim", args).await?;
    let _ = stop.send(true);
    let _ = task.await;
    emcy_flood(args, pki, dir).await?;
    cpu_per_request(args, pki, hub.local_addr(), dir).await?;
    memory(args, pki, &bus, dir).await?;
    sim.stop().await;
    hub.shutdown().await;
    binary_size(&args.exe()?, dir)
}
