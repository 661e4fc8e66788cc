//! `socketcand://HOST:PORT/CHANNEL`: a raw-mode socketcand client that survives outages.
//!
//! [`SharedLink::open`] connects and completes the handshake (`< hi >`, `< open CHANNEL >`,
//! `< rawmode >`) before it returns, so a wrong address fails at once. Afterwards one task owns
//! the connection: it reads frames into the receive queues of the link's endpoints, and writes
//! what senders could not write themselves. A send writes its frame to the socket at once when
//! nothing is waiting before it and no send has since the task last ran (no hand-over to the
//! task and no wake-up of it: an SDO request goes out from the task that makes it); otherwise,
//! or when the socket takes only part, the frame waits in order behind the others and the task
//! writes them, as many per TCP write as have collected (a block transfer's segments). A frame one
//! endpoint sends reaches the link's other endpoints at once, as the server would have delivered
//! it to them over connections of their own. When the link breaks every receiver gets
//! [`BusEvent::LinkDown`], sends fail with [`BusError::Offline`], and the task reconnects with
//! capped full-jitter backoff until it succeeds ([`BusEvent::LinkUp`]) or every endpoint and
//! handle is dropped.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant, SystemTime};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::TcpStream;
use tokio::sync::{mpsc, oneshot, Notify};

use super::codec::{self, DecodeError, Decoder, Message};
use crate::backoff::Backoff;
use crate::bus::{BusError, BusEvent, BusOptions, BusSender, Endpoints, RxFeed, SenderInner};
use crate::frame::{Frame, FrameKind};

/// How long connecting plus the handshake may take.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(5);
/// Bytes of encoded frames waiting for the link's task before `send` waits (about a thousand
/// frames).
const TX_QUEUE_BYTES: usize = 48 * 1024;
/// A link that stayed up this long resets the reconnect backoff.
const STABLE_LINK: Duration = Duration::from_secs(60);

struct Link {
    name: String,
    online: AtomicBool,
    endpoints: Endpoints,
    out: Mutex<Outgoing>,
    /// Wakes the link's task: bytes wait in `out` for it.
    wanted: Notify,
    /// Wakes senders waiting for room in `out`: the task wrote what waited.
    drained: Notify,
}

/// What goes to the server: the connection's writing half, and the bytes that wait for it.
#[derive(Default)]
struct Outgoing {
    /// While the link is up.
    writer: Option<Arc<OwnedWriteHalf>>,
    /// Encoded frames not yet written, in order; a frame's rest when the socket took only part.
    waiting: Vec<u8>,
    /// The task is writing what waited: new frames wait behind it, not write past it.
    busy: bool,
    /// A send wrote to the socket itself since the link's task last ran: the next frames wait
    /// for the task, which writes them together. A sender of many frames in a row (an SDO
    /// block) thus costs a system call per batch, not per frame, while a lone frame (an SDO
    /// request, answered before the next) still goes out at once.
    recent: bool,
}

impl Link {
    fn out(&self) -> MutexGuard<'_, Outgoing> {
        self.out.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// The link's task takes requests to confirm that everything sent before is written; the
/// channel's senders also tell it whether anyone can still send.
type FlushRequest = oneshot::Sender<()>;

/// The sending side of a `socketcand://` endpoint.
#[derive(Clone)]
pub(crate) struct ClientSender {
    tx: mpsc::Sender<FlushRequest>,
    link: Arc<Link>,
    endpoint: u64,
}

impl ClientSender {
    pub(crate) async fn send(&self, frame: Frame) -> Result<(), BusError> {
        if frame.kind() != FrameKind::Data {
            return Err(BusError::Unsupported(
                "socketcand raw mode carries data frames only (no remote or error frames)".into(),
            ));
        }
        let mut text = String::with_capacity(48);
        codec::encode_send(&frame, &mut text);
        loop {
            let room = self.link.drained.notified();
            tokio::pin!(room);
            room.as_mut().enable();
            {
                let mut out = self.link.out();
                if !self.link.online.load(Ordering::Acquire) {
                    return Err(BusError::Offline {
                        link: self.link.name.clone(),
                    });
                }
                if out.waiting.len() < TX_QUEUE_BYTES {
                    let rest = match &out.writer {
                        Some(writer) if !out.busy && !out.recent && out.waiting.is_empty() => {
                            match writer.try_write(text.as_bytes()) {
                                Ok(n) => &text.as_bytes()[n..],
                                // Would block, or failed: the task writes it and sees why.
                                Err(_) => text.as_bytes(),
                            }
                        }
                        _ => text.as_bytes(),
                    };
                    if rest.is_empty() {
                        out.recent = true;
                    } else {
                        out.waiting.extend_from_slice(rest);
                        self.link.wanted.notify_one();
                    }
                    break;
                }
            }
            room.await;
        }
        self.link
            .endpoints
            .deliver(Some(self.endpoint), frame.with_timestamp(SystemTime::now()));
        Ok(())
    }

    /// Wait until every frame sent so far is written to the socket.
    pub(crate) async fn flush(&self) -> Result<(), BusError> {
        let (done, written) = oneshot::channel();
        self.tx.send(done).await.map_err(|_| BusError::Closed)?;
        written.await.map_err(|_| BusError::Offline {
            link: self.link.name.clone(),
        })
    }
}

struct Connection {
    reader: OwnedReadHalf,
    writer: OwnedWriteHalf,
    decoder: Decoder,
}

async fn expect(
    stream: &mut TcpStream,
    decoder: &mut Decoder,
    wanted: Message,
) -> Result<(), BusError> {
    loop {
        match decoder.next_message() {
            Some(Ok(m)) if m == wanted => return Ok(()),
            Some(Ok(Message::Error(text))) => {
                return Err(BusError::Protocol(format!(
                    "socketcand refused ({wanted:?}): {text}"
                )))
            }
            Some(other) => {
                return Err(BusError::Protocol(format!(
                    "socketcand handshake: expected {wanted:?}, got {other:?}"
                )))
            }
            None => {}
        }
        read_more(stream, decoder).await?;
    }
}

/// Read what the server sent next into `decoder`.
async fn read_more(stream: &mut TcpStream, decoder: &mut Decoder) -> Result<(), BusError> {
    let mut buf = [0u8; 512];
    let n = stream
        .read(&mut buf)
        .await
        .map_err(|e| BusError::io("socketcand handshake", e))?;
    if n == 0 {
        return Err(BusError::Protocol(
            "socketcand closed the connection during the handshake".into(),
        ));
    }
    decoder.feed(&buf[..n]);
    Ok(())
}

/// How long `settle` waits for the `< echo >` answer before going on without it.
const SETTLE_TIMEOUT: Duration = Duration::from_secs(1);

/// Wait until the server delivers frames to us: the hub (and socketcand implementations like
/// it) holds frames back for a moment after the raw-mode `< ok >`, and a tool that sends a
/// request right after opening the bus (an LSS Fastscan step listens 20–50 ms) would miss the
/// answer. `< echo >` is answered in the order of the outgoing queue, so its answer comes after
/// the hold. Frames before it were on the bus while `Bus::open` had not returned; they are
/// dropped. A server that does not answer echo costs [`SETTLE_TIMEOUT`] once.
async fn settle(stream: &mut TcpStream, decoder: &mut Decoder) -> Result<(), BusError> {
    stream
        .write_all(codec::encode_control(&Message::Echo).as_bytes())
        .await
        .map_err(|e| BusError::io("socketcand handshake", e))?;
    let wait = async {
        loop {
            while let Some(message) = decoder.next_message() {
                if matches!(message, Ok(Message::Echo)) {
                    return Ok(());
                }
            }
            read_more(stream, decoder).await?;
        }
    };
    match tokio::time::timeout(SETTLE_TIMEOUT, wait).await {
        Ok(result) => result,
        Err(_) => {
            tracing::debug!("socketcand did not answer < echo >; going on");
            Ok(())
        }
    }
}

async fn connect(host: &str, port: u16, channel: &str) -> Result<Connection, BusError> {
    let handshake = async {
        let mut stream = TcpStream::connect((host, port))
            .await
            .map_err(|e| BusError::io(format!("connecting to socketcand at {host}:{port}"), e))?;
        stream
            .set_nodelay(true)
            .map_err(|e| BusError::io("setting TCP_NODELAY", e))?;
        let mut decoder = Decoder::new();
        expect(&mut stream, &mut decoder, Message::Hi).await?;
        let open = codec::encode_control(&Message::Open(channel.to_owned()));
        stream
            .write_all(open.as_bytes())
            .await
            .map_err(|e| BusError::io("socketcand handshake", e))?;
        expect(&mut stream, &mut decoder, Message::Ok).await?;
        stream
            .write_all(b"< rawmode >")
            .await
            .map_err(|e| BusError::io("socketcand handshake", e))?;
        expect(&mut stream, &mut decoder, Message::Ok).await?;
        settle(&mut stream, &mut decoder).await?;
        let (reader, writer) = stream.into_split();
        Ok(Connection {
            reader,
            writer,
            decoder,
        })
    };
    tokio::time::timeout(HANDSHAKE_TIMEOUT, handshake)
        .await
        .map_err(|_| {
            BusError::Protocol(format!(
                "socketcand at {host}:{port} did not complete the handshake in {HANDSHAKE_TIMEOUT:?}"
            ))
        })?
}

/// One connection to a socketcand server, shared by the endpoints of an
/// [`Interface`](crate::Interface).
#[derive(Clone)]
pub(crate) struct SharedLink {
    tx: mpsc::Sender<FlushRequest>,
    link: Arc<Link>,
}

impl SharedLink {
    pub(crate) async fn open(host: &str, port: u16, channel: &str) -> Result<SharedLink, BusError> {
        let conn = connect(host, port, channel).await?;
        let link = Arc::new(Link {
            name: format!("socketcand://{host}:{port}/{channel}"),
            online: AtomicBool::new(true),
            endpoints: Endpoints::default(),
            out: Mutex::default(),
            wanted: Notify::new(),
            drained: Notify::new(),
        });
        let (tx, rx) = mpsc::channel(16);
        let target = (host.to_owned(), port, channel.to_owned());
        tokio::spawn(supervise(conn, target, link.clone(), rx));
        Ok(SharedLink { tx, link })
    }

    /// A new endpoint on this link, fed by `feed`.
    pub(crate) fn endpoint(&self, feed: RxFeed, options: &BusOptions) -> BusSender {
        let endpoint = self.link.endpoints.add(feed, options.receive_own);
        BusSender::new(SenderInner::Socketcand(ClientSender {
            tx: self.tx.clone(),
            link: self.link.clone(),
            endpoint,
        }))
    }
}

/// Why a connection ended.
enum End {
    Lost(String),
    Shutdown,
}

async fn supervise(
    mut conn: Connection,
    (host, port, channel): (String, u16, String),
    link: Arc<Link>,
    mut frames: mpsc::Receiver<FlushRequest>,
) {
    let mut backoff = Backoff::new(Duration::from_millis(100), Duration::from_secs(10));
    loop {
        let since = Instant::now();
        let reason = match run(conn, &mut frames, &link).await {
            End::Shutdown => return,
            End::Lost(reason) => reason,
        };
        link.online.store(false, Ordering::Release);
        let dropped = {
            let mut out = link.out();
            out.writer = None;
            out.busy = false;
            // Each encoded frame ends with `>`, also the rest of one the socket took part of.
            let dropped = out.waiting.iter().filter(|&&b| b == b'>').count();
            out.waiting = Vec::new();
            dropped
        };
        link.drained.notify_waiters();
        // Flushes asked meanwhile are answered by the channel's end: their frames are gone.
        while frames.try_recv().is_ok() {}
        tracing::warn!(link = %link.name, %reason, dropped, "bus link down; reconnecting");
        link.endpoints
            .announce(BusEvent::LinkDown {
                reason: format!("{reason} ({dropped} queued frame(s) not sent)"),
            })
            .await;
        if since.elapsed() >= STABLE_LINK {
            backoff.reset();
        }
        conn = loop {
            let delay = backoff.next_delay();
            tokio::select! {
                _ = tokio::time::sleep(delay) => {}
                _ = link.endpoints.closed(), if frames.sender_strong_count() == 0 => return,
            }
            if frames.sender_strong_count() == 0 && link.endpoints.prune() {
                return;
            }
            match connect(&host, port, &channel).await {
                Ok(conn) => break conn,
                Err(e) => tracing::debug!(link = %link.name, error = %e, "reconnect failed"),
            }
        };
        link.online.store(true, Ordering::Release);
        tracing::info!(link = %link.name, "bus link up again");
        link.endpoints.announce(BusEvent::LinkUp).await;
    }
}

async fn run(conn: Connection, flushes: &mut mpsc::Receiver<FlushRequest>, link: &Link) -> End {
    let Connection {
        mut reader,
        writer,
        mut decoder,
    } = conn;
    let writer = Arc::new(writer);
    link.out().writer = Some(writer.clone());
    tokio::select! {
        end = read_loop(&mut reader, &mut decoder, link) => end,
        end = write_loop(&writer, flushes, link) => end,
    }
}

async fn read_loop(reader: &mut OwnedReadHalf, decoder: &mut Decoder, link: &Link) -> End {
    let mut buf = vec![0u8; 16 * 1024];
    let mut reported = 0u32;
    loop {
        while let Some(message) = decoder.next_message() {
            match message {
                Ok(Message::Frame(frame)) => link.endpoints.deliver(None, frame),
                Ok(Message::Echo) | Ok(Message::Ok) => {}
                Ok(other) => tracing::warn!(?other, "unexpected socketcand message in raw mode"),
                Err(DecodeError::Oversized) => {
                    return End::Lost("socketcand sent an oversized message".into())
                }
                Err(e) if reported < 10 => {
                    reported += 1;
                    tracing::warn!(error = %e, "bad data from socketcand dropped");
                }
                Err(_) => {}
            }
        }
        match reader.read(&mut buf).await {
            Ok(0) => return End::Lost("connection closed by the server".into()),
            Ok(n) => {
                // The link's task ran: the next send may write to the socket itself again
                // (before the frames read are delivered, so that a request sent in answer to
                // them does).
                link.out().recent = false;
                decoder.feed(&buf[..n]);
            }
            Err(e) => return End::Lost(format!("read failed: {e}")),
        }
    }
}

/// Write what senders left waiting, and answer flushes once all that was sent before them is
/// written.
async fn write_loop(
    writer: &OwnedWriteHalf,
    flushes: &mut mpsc::Receiver<FlushRequest>,
    link: &Link,
) -> End {
    let mut batch = Vec::new();
    let mut flushed: Vec<FlushRequest> = Vec::new();
    loop {
        {
            let mut out = link.out();
            std::mem::swap(&mut batch, &mut out.waiting);
            out.busy = !batch.is_empty();
            out.recent = false;
        }
        if !batch.is_empty() {
            if let Err(e) = write_all(writer, &batch).await {
                return End::Lost(format!("write failed: {e}"));
            }
            batch.clear();
            link.drained.notify_waiters();
            // What senders left meanwhile goes next, before anyone writes past it.
            continue;
        }
        // Nothing waits: frames sent before a flush request are on the socket.
        for done in flushed.drain(..) {
            let _ = done.send(());
        }
        tokio::select! {
            () = link.wanted.notified() => {}
            request = flushes.recv() => match request {
                Some(done) => flushed.push(done),
                None => {
                    // Every sender is gone: keep receiving until the receivers are gone too.
                    link.endpoints.closed().await;
                    return End::Shutdown;
                }
            },
        }
    }
}

async fn write_all(writer: &OwnedWriteHalf, mut bytes: &[u8]) -> std::io::Result<()> {
    while !bytes.is_empty() {
        writer.writable().await?;
        match writer.try_write(bytes) {
            Ok(0) => return Err(std::io::ErrorKind::WriteZero.into()),
            Ok(n) => bytes = &bytes[n..],
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {}
            Err(e) => return Err(e),
        }
    }
    Ok(())
}
