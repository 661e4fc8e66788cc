//! `socketcand://HOST:PORT/CHANNEL`: a raw-mode socketcand client that survives outages.
//!
//! [`SharedLink::open`] connects and completes the handshake (`< hi >`, `< open CHANNEL >`,
//! `< rawmode >`) before it returns, so a wrong address fails at once. Afterwards one task owns
//! the connection: it writes queued frames (batched into as few TCP segments as the queue allows)
//! and reads frames into the receive queues of the link's endpoints concurrently. A frame one
//! endpoint sends reaches the link's other endpoints at once, as the server would have delivered
//! it to them over connections of their own. When the link breaks every receiver gets
//! [`BusEvent::LinkDown`], sends fail with [`BusError::Offline`], and the task reconnects with
//! capped full-jitter backoff until it succeeds ([`BusEvent::LinkUp`]) or every endpoint and
//! handle is dropped.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime};

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::TcpStream;
use tokio::sync::{mpsc, oneshot};

use super::codec::{self, DecodeError, Decoder, Message};
use crate::backoff::Backoff;
use crate::bus::{BusError, BusEvent, BusOptions, BusSender, Endpoints, RxFeed, SenderInner};
use crate::frame::{Frame, FrameKind};

/// How long connecting plus the handshake may take.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(5);
/// Frames queued for transmission before `send` waits.
const TX_QUEUE: usize = 1024;
/// Frames written per TCP write at most.
const TX_BATCH: usize = 64;
/// A link that stayed up this long resets the reconnect backoff.
const STABLE_LINK: Duration = Duration::from_secs(60);

struct Link {
    name: String,
    online: AtomicBool,
    endpoints: Endpoints,
}

/// What the writer task takes: frames, and requests to confirm everything before is written.
enum Tx {
    Frame(Frame),
    Flush(oneshot::Sender<()>),
}

/// The sending side of a `socketcand://` endpoint.
#[derive(Clone)]
pub(crate) struct ClientSender {
    tx: mpsc::Sender<Tx>,
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
        if !self.link.online.load(Ordering::Acquire) {
            return Err(BusError::Offline {
                link: self.link.name.clone(),
            });
        }
        self.tx
            .send(Tx::Frame(frame))
            .await
            .map_err(|_| BusError::Closed)?;
        self.link
            .endpoints
            .deliver(Some(self.endpoint), frame.with_timestamp(SystemTime::now()));
        Ok(())
    }

    /// Wait until every frame queued so far is written to the socket.
    pub(crate) async fn flush(&self) -> Result<(), BusError> {
        let (done, written) = oneshot::channel();
        self.tx
            .send(Tx::Flush(done))
            .await
            .map_err(|_| BusError::Closed)?;
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
    tx: mpsc::Sender<Tx>,
    link: Arc<Link>,
}

impl SharedLink {
    pub(crate) async fn open(host: &str, port: u16, channel: &str) -> Result<SharedLink, BusError> {
        let conn = connect(host, port, channel).await?;
        let link = Arc::new(Link {
            name: format!("socketcand://{host}:{port}/{channel}"),
            online: AtomicBool::new(true),
            endpoints: Endpoints::default(),
        });
        let (tx, rx) = mpsc::channel(TX_QUEUE);
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
    mut frames: mpsc::Receiver<Tx>,
) {
    let mut backoff = Backoff::new(Duration::from_millis(100), Duration::from_secs(10));
    loop {
        let since = Instant::now();
        let reason = match run(conn, &mut frames, &link.endpoints).await {
            End::Shutdown => return,
            End::Lost(reason) => reason,
        };
        link.online.store(false, Ordering::Release);
        let dropped = std::iter::from_fn(|| frames.try_recv().ok()).count();
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

async fn run(conn: Connection, frames: &mut mpsc::Receiver<Tx>, endpoints: &Endpoints) -> End {
    let Connection {
        mut reader,
        writer,
        mut decoder,
    } = conn;
    tokio::select! {
        end = read_loop(&mut reader, &mut decoder, endpoints) => end,
        end = write_loop(writer, frames, endpoints) => end,
    }
}

async fn read_loop(
    reader: &mut OwnedReadHalf,
    decoder: &mut Decoder,
    endpoints: &Endpoints,
) -> End {
    let mut buf = vec![0u8; 16 * 1024];
    let mut reported = 0u32;
    loop {
        while let Some(message) = decoder.next_message() {
            match message {
                Ok(Message::Frame(frame)) => endpoints.deliver(None, frame),
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
            Ok(n) => decoder.feed(&buf[..n]),
            Err(e) => return End::Lost(format!("read failed: {e}")),
        }
    }
}

async fn write_loop(
    mut writer: OwnedWriteHalf,
    frames: &mut mpsc::Receiver<Tx>,
    endpoints: &Endpoints,
) -> End {
    let mut text = String::with_capacity(TX_BATCH * 48);
    let mut flushed = Vec::new();
    loop {
        let Some(first) = frames.recv().await else {
            // Every sender is gone: keep receiving until the receivers are gone too.
            endpoints.closed().await;
            return End::Shutdown;
        };
        text.clear();
        let mut next = Some(first);
        let mut batched = 0;
        while let Some(item) = next.take() {
            match item {
                Tx::Frame(frame) => codec::encode_send(&frame, &mut text),
                Tx::Flush(done) => flushed.push(done),
            }
            batched += 1;
            if batched < TX_BATCH {
                next = frames.try_recv().ok();
            }
        }
        if let Err(e) = writer.write_all(text.as_bytes()).await {
            return End::Lost(format!("write failed: {e}"));
        }
        for done in flushed.drain(..) {
            let _ = done.send(());
        }
    }
}
