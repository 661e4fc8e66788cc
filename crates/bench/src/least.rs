//! The least CPU a bus-node gateway's request can cost on this machine through the hub: a
//! thread making only the system calls a request on one SDO channel needs — the SDO upload
//! request written to the hub, a blocking read until the controller's answer (one transfer at
//! a time on a channel, CiA 301 §7.2.4.3, so the thread sleeps until it comes), 200 bytes
//! written to a socket for the portal — with no TLS, no JSON and no async runtime. What the
//! gateway spends above it is its own (docs/BENCHMARKS.md §The bus-node gateway on its default
//! channel, counted).

use std::io::{Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};

use anyhow::{bail, Context};
use canbus::socketcand::codec::{self, Decoder, Message};
use canbus::Frame;
use canopen::sdo::msg::{Request, Response};

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

/// `requests` SDO uploads of 6520h sub 1 from the simulated controller (node 1, its default
/// channel) through the hub at `hub`, each answered with 200 bytes to a socket whose reader is
/// another thread; blocking, so call it from a thread that may block.
pub(crate) fn measure(hub: SocketAddr, requests: usize) -> anyhow::Result<Least> {
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
    let request = {
        let payload = Request::InitiateUpload {
            index: INDEX,
            sub: SUB,
        }
        .write();
        let mut text = String::new();
        codec::encode_send(&Frame::standard(0x601, &payload)?, &mut text);
        text.into_bytes()
    };
    let answer = [b' '; ANSWER];
    // Warm up, then measure.
    for _ in 0..requests.min(200) {
        bus.ask(&request)?;
    }
    let before = crate::process::thread_schedstat().context("/proc/thread-self/schedstat")?;
    for _ in 0..requests {
        bus.ask(&request)?;
        portal.write_all(&answer)?;
    }
    let (cpu, slices) = crate::process::thread_schedstat()
        .map(|(cpu, slices)| {
            (
                cpu.saturating_sub(before.0),
                slices.saturating_sub(before.1),
            )
        })
        .context("/proc/thread-self/schedstat")?;
    drop(portal);
    let _ = drain.join();
    let n = requests.max(1) as f64;
    Ok(Least {
        cpu_us: cpu.as_secs_f64() * 1e6 / n,
        wakeups: slices as f64 / n,
    })
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

    /// Write `request` (an encoded SDO upload request) and read until the controller's answer.
    fn ask(&mut self, request: &[u8]) -> anyhow::Result<()> {
        self.socket.write_all(request)?;
        loop {
            if let Message::Frame(frame) = self.next()? {
                if frame.id().as_raw() != 0x581 {
                    continue;
                }
                // An SDO frame is 8 bytes (CiA 301 §7.2.4.3), as the SDO client takes it.
                let Some(payload) = canopen::sdo::payload(frame.data()) else {
                    continue;
                };
                return match Response::read(&payload) {
                    Ok(Response::InitiateUpload { index, sub, .. })
                        if (index, sub) == (INDEX, SUB) =>
                    {
                        Ok(())
                    }
                    other => bail!("the controller answered {other:?}"),
                };
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
