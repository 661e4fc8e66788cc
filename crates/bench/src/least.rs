//! The least CPU a bus-node gateway's request can cost on this machine through the hub, two
//! ways. First a thread making only the system calls a request on one SDO channel needs — the SDO
//! upload request written to the hub, a blocking read until the controller's answer (one transfer
//! at a time on a channel, CiA 301 §7.2.4.3, so the thread sleeps until it comes), 200 bytes
//! written to a socket for the portal — with no TLS, no JSON and no async runtime. Then the same
//! thread doing the connector's own work as well, with the project's sans-IO cores and no
//! runtime: the portal's request opened from its TLS record and WebSocket frame, taken by the
//! NXg session, its read started by the SDO client and written as socketcand text; the answer
//! advanced through the SDO client and the session and sealed into a masked frame and a TLS
//! record. That is what a gateway restructured into one sans-IO step per wake-up would cost; the
//! same work in a loop without sleeping says how much of it is the work and how much the wake-up.
//! What the gateway spends above them is its async edges' (docs/BENCHMARKS.md §The bus-node
//! gateway on its default channel, counted; §The floor of a restructured gateway).

use std::io::{Cursor, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context as _};
use canbus::socketcand::codec::{self, Decoder, Message};
use canbus::Frame;
use canopen::sdo::client::{ClientConfig, SdoClient, Transfer};
use canopen::sdo::msg::{Initiate, Request, Response};
use canopen::sdo::Payload;
use cloud::devpki::DevPki;
use gateway::config::Config;
use gateway::metadata::BusMetadata;
use lift417::catalog::{Catalog, Device};
use nxg::gateway::{Context, Job, JobId, JobResult, Output, Phase, Session, Target};
use rustls::{ClientConnection, ServerConnection};
use tokio_tungstenite::tungstenite::protocol::frame::coding::{Data, OpCode};
use tokio_tungstenite::tungstenite::protocol::frame::{Frame as WsFrame, FrameHeader};

/// The object read, as the gateway benchmark's naked gets read it: 6520h sub 1 of node 1.
const INDEX: u16 = 0x6520;
const SUB: u8 = 1;

/// The size of an answer to the portal: a naked get's JSON-RPC response in a TLS record.
const ANSWER: usize = 200;

/// What one request cost the measuring thread.
pub(crate) struct Least {
    /// CPU time (user and system), µs.
    pub cpu_us: f64,
    /// Times the thread was put on a CPU (each sleep ends in one).
    pub wakeups: f64,
}

/// The gateway's part of a request, as the measuring loop drives it.
trait Part {
    /// The next request's SDO frame to the hub (socketcand text).
    fn ask(&mut self) -> anyhow::Result<&[u8]>;
    /// The controller's answer on 581h; what goes to the portal.
    fn answer(&mut self, payload: &Payload) -> anyhow::Result<&[u8]>;
}

/// The system calls alone: a fixed request, the answer checked, 200 bytes for the portal.
struct Bare {
    request: Vec<u8>,
    answer: [u8; ANSWER],
}

impl Bare {
    fn new() -> anyhow::Result<Bare> {
        let payload = Request::InitiateUpload {
            index: INDEX,
            sub: SUB,
        }
        .write();
        let mut text = String::new();
        codec::encode_send(&Frame::standard(0x601, &payload)?, &mut text);
        Ok(Bare {
            request: text.into_bytes(),
            answer: [b' '; ANSWER],
        })
    }
}

impl Part for Bare {
    fn ask(&mut self) -> anyhow::Result<&[u8]> {
        Ok(&self.request)
    }

    fn answer(&mut self, payload: &Payload) -> anyhow::Result<&[u8]> {
        match Response::read(payload) {
            Ok(Response::InitiateUpload { index, sub, .. }) if (index, sub) == (INDEX, SUB) => {
                Ok(&self.answer)
            }
            other => bail!("the controller answered {other:?}"),
        }
    }
}

/// `requests` SDO uploads of 6520h sub 1 from the simulated controller (node 1, its default
/// channel) through the hub at `hub`, each answered with 200 bytes to a socket whose reader is
/// another thread; blocking, so call it from a thread that may block.
pub(crate) fn measure(hub: SocketAddr, requests: usize) -> anyhow::Result<Least> {
    run(hub, requests, &mut Bare::new()?)
}

/// The same with the connector's own work done by the project's sans-IO cores (the module's
/// comment); and that work alone, `requests` times in a loop with the controller's answer made
/// in memory, no system call and no sleep: CPU µs per request.
pub(crate) fn measure_sans_io(
    hub: SocketAddr,
    requests: usize,
    pki: &DevPki,
) -> anyhow::Result<(Least, f64)> {
    let least = run(hub, requests, &mut Connector::new(pki, WARM_UP + requests)?)?;
    let mut part = Connector::new(pki, WARM_UP + requests)?;
    let answer = Response::InitiateUpload {
        index: INDEX,
        sub: SUB,
        data: Initiate::Expedited {
            data: &part.value,
            sized: true,
        },
    }
    .write();
    let hot = measured(requests, || {
        std::hint::black_box(part.ask()?);
        std::hint::black_box(part.answer(&answer)?);
        Ok(())
    })?;
    Ok((least, hot.cpu_us))
}

/// Requests made before the measured ones: first reads, allocations, caches.
const WARM_UP: usize = 200;

/// What `requests` calls of `one` cost this thread, after up to [`WARM_UP`] calls unmeasured.
fn measured(requests: usize, mut one: impl FnMut() -> anyhow::Result<()>) -> anyhow::Result<Least> {
    for _ in 0..requests.min(WARM_UP) {
        one()?;
    }
    let schedstat = || crate::process::thread_schedstat().context("/proc/thread-self/schedstat");
    let (cpu, slices) = schedstat()?;
    for _ in 0..requests {
        one()?;
    }
    let (cpu_after, slices_after) = schedstat()?;
    let n = requests.max(1) as f64;
    Ok(Least {
        cpu_us: cpu_after.saturating_sub(cpu).as_secs_f64() * 1e6 / n,
        wakeups: slices_after.saturating_sub(slices) as f64 / n,
    })
}

fn run(hub: SocketAddr, requests: usize, part: &mut impl Part) -> anyhow::Result<Least> {
    let sink = TcpListener::bind(SocketAddr::from(([127, 0, 0, 1], 0)))?;
    let mut portal = TcpStream::connect(sink.local_addr()?)?;
    portal.set_nodelay(true)?;
    let (reader, _) = sink.accept()?;
    let drain = std::thread::spawn(move || {
        let mut reader = reader;
        let mut buf = [0u8; 64 * 1024];
        while matches!(reader.read(&mut buf), Ok(n) if n > 0) {}
    });
    let mut bus = Bus::open(hub)?;
    let least = measured(requests, || {
        let answer = bus.ask(part.ask()?)?;
        portal.write_all(part.answer(&answer)?)?;
        Ok(())
    })?;
    drop(portal);
    let _ = drain.join();
    Ok(least)
}

/// The connector's work on a request with the project's sans-IO cores, no runtime: what one
/// step per wake-up of a restructured gateway would do.
struct Connector {
    session: Session,
    /// What the controller's dictionary holds: its answer in the loop without round trips.
    value: Vec<u8>,
    sdo: SdoClient,
    job: Option<JobId>,
    tls: ClientConnection,
    /// The portal's requests as it sends them, one TLS record each (sealed beforehand: the
    /// portal's work is not the gateway's), taken from the back.
    records: Vec<Vec<u8>>,
    plain: Vec<u8>,
    frames: Vec<Payload>,
    text: String,
    out: Vec<u8>,
}

impl Connector {
    fn new(pki: &DevPki, requests: usize) -> anyhow::Result<Connector> {
        let now = Instant::now();
        let (tls, mut portal) = tls_pair(pki)?;
        let mut records = Vec::with_capacity(requests);
        for id in 0..requests {
            let mut frame = Vec::new();
            WsFrame::message(
                crate::gets::get(id, "0x652001", "naked").into_bytes(),
                OpCode::Data(Data::Text),
                true,
            )
            .format(&mut frame)?;
            portal.writer().write_all(&frame)?;
            let mut record = Vec::new();
            portal.write_tls(&mut record)?;
            records.push(record);
        }
        records.reverse();
        let mut config = Config::default();
        config.identity.sernum = "least".into();
        let od = Catalog::builtin()
            .dictionary(Device::Controller, 1, 8)
            .context("the catalog makes a controller's dictionary")?;
        let value = od
            .read(INDEX, SUB)
            .context("the controller has 6520h sub 1")?;
        let metadata = BusMetadata::load(&config)?.with_dictionary(TARGET, Arc::new(od));
        let mut session = Session::new(
            config.settings(),
            Context::new(Arc::new(metadata)),
            None,
            now,
        );
        let _ = session.connect();
        let _ = session.handle_text(
            r#"{"jsonrpc":"2.0","id":1,"result":"CONNACK","api":1}"#,
            now,
        );
        if !matches!(session.phase(), Phase::Connected(_)) {
            bail!("the session did not take the CONNACK");
        }
        Ok(Connector {
            session,
            value,
            sdo: SdoClient::new(ClientConfig::default()),
            job: None,
            tls,
            records,
            plain: Vec::new(),
            frames: Vec::new(),
            text: String::new(),
            out: Vec::new(),
        })
    }
}

impl Part for Connector {
    fn ask(&mut self) -> anyhow::Result<&[u8]> {
        let now = Instant::now();
        let record = self.records.pop().context("no request left")?;
        self.tls.read_tls(&mut record.as_slice())?;
        self.tls.process_new_packets()?;
        self.plain.clear();
        match self.tls.reader().read_to_end(&mut self.plain) {
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
            other => {
                other?;
            }
        }
        let mut cursor = Cursor::new(self.plain.as_slice());
        let (_, len) = FrameHeader::parse(&mut cursor)?.context("a whole frame")?;
        let at = usize::try_from(cursor.position())?;
        let payload = self
            .plain
            .get(at..at + usize::try_from(len)?)
            .context("a whole frame")?;
        let text = std::str::from_utf8(payload)?;
        for output in self.session.handle_text(text, now) {
            if let Output::Start(id, Job::Read { target, index, sub }) = output {
                if target != TARGET {
                    bail!("a read of {target:?}");
                }
                self.frames.clear();
                self.sdo
                    .start_upload(index, sub, Transfer::Normal, now, &mut self.frames)?;
                self.job = Some(id);
            }
        }
        self.text.clear();
        for frame in &self.frames {
            codec::encode_send(&Frame::standard(0x601, frame)?, &mut self.text);
        }
        Ok(self.text.as_bytes())
    }

    fn answer(&mut self, payload: &Payload) -> anyhow::Result<&[u8]> {
        let now = Instant::now();
        self.frames.clear();
        let value = match self.sdo.handle(payload, now, &mut self.frames) {
            Some(outcome) => outcome?,
            None => bail!("an upload of more than one frame"),
        };
        let job = self.job.take().context("no read under way")?;
        self.out.clear();
        for output in self
            .session
            .handle_job(job, JobResult::Read(vec![value]), now)
        {
            if let Output::Send(text) = output {
                let mut frame = WsFrame::message(text.into_bytes(), OpCode::Data(Data::Text), true);
                // A client masks what it sends (RFC 6455 §5.3); the mask's randomness is not
                // what is measured, the masking is.
                frame.header_mut().mask = Some(MASK);
                self.plain.clear();
                frame.format(&mut self.plain)?;
                self.tls.writer().write_all(&self.plain)?;
            }
        }
        self.tls.write_tls(&mut self.out)?;
        Ok(&self.out)
    }
}

/// The WebSocket mask of the gateway's frames.
const MASK: [u8; 4] = [0x5a, 0xc3, 0x0f, 0x96];

/// The controller's node the reads go to.
const TARGET: Target = Target { net: 1, node: 1 };

/// A TLS connection of the gateway to the portal, handshaken in memory.
fn tls_pair(pki: &DevPki) -> anyhow::Result<(ClientConnection, ServerConnection)> {
    let client_config = tls::client_config(Some(&pki.ca), None)?;
    let server_config = Arc::new(tls::server_config(&pki.cert, &pki.key, None)?);
    let mut client = ClientConnection::new(client_config, "localhost".try_into()?)?;
    let mut server = ServerConnection::new(server_config)?;
    let mut wire = Vec::new();
    while client.wants_write() || server.wants_write() || client.is_handshaking() {
        wire.clear();
        client.write_tls(&mut wire)?;
        server.read_tls(&mut wire.as_slice())?;
        server.process_new_packets()?;
        wire.clear();
        server.write_tls(&mut wire)?;
        client.read_tls(&mut wire.as_slice())?;
        client.process_new_packets()?;
    }
    Ok((client, server))
}

/// A socketcand client of the hub in raw mode, read and written with blocking calls.
struct Bus {
    socket: TcpStream,
    decoder: Decoder,
}

impl Bus {
    fn open(hub: SocketAddr) -> anyhow::Result<Bus> {
        let socket = TcpStream::connect(hub)?;
        socket.set_nodelay(true)?;
        let mut bus = Bus {
            socket,
            decoder: Decoder::new(),
        };
        bus.expect(Message::Hi)?;
        for command in [Message::Open("can0".into()), Message::RawMode] {
            bus.socket
                .write_all(codec::encode_control(&command).as_bytes())?;
            bus.expect(Message::Ok)?;
        }
        Ok(bus)
    }

    /// Write `request` (an encoded SDO request) and read until the controller's answer on
    /// 581h.
    fn ask(&mut self, request: &[u8]) -> anyhow::Result<Payload> {
        self.socket.write_all(request)?;
        loop {
            if let Message::Frame(frame) = self.next()? {
                if frame.id().as_raw() != 0x581 {
                    continue;
                }
                // An SDO frame is 8 bytes (CiA 301 §7.2.4.3), as the SDO client takes it.
                if let Some(payload) = canopen::sdo::payload(frame.data()) {
                    return Ok(payload);
                }
            }
        }
    }

    fn expect(&mut self, wanted: Message) -> anyhow::Result<()> {
        match self.next()? {
            message if message == wanted => Ok(()),
            other => bail!("the hub said {other:?}, not {wanted:?}"),
        }
    }

    /// The next message from the hub, reading (and sleeping) when none is buffered.
    fn next(&mut self) -> anyhow::Result<Message> {
        loop {
            if let Some(message) = self.decoder.next_message() {
                return Ok(message?);
            }
            let mut buf = [0u8; 4096];
            let n = self.socket.read(&mut buf)?;
            if n == 0 {
                bail!("the hub closed the connection");
            }
            self.decoder.feed(&buf[..n]);
        }
    }
}
