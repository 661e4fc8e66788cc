//! The server side of TLS over a tokio byte stream that holds no buffer while the connection is
//! idle, on rustls's unbuffered API.
//!
//! A portal holds thousands of gateway connections that say something every few minutes. A
//! buffered rustls connection (what `tokio-rustls` wraps) keeps a 4 KiB record buffer from its
//! first read until it closes — a quarter of what an idle connection costs the portal
//! (docs/BENCHMARKS.md §Where an idle gateway connection's memory goes). [`ServerStream`] owns its
//! buffers instead and lets each go as soon as it is empty: the TLS bytes received but not yet
//! decrypted, the plaintext not yet read, the records not yet written. An idle connection keeps
//! only rustls's connection state.
//!
//! Reads decrypt every complete record at once and copy the plaintext straight into the
//! caller's buffer, keeping what does not fit; writes encrypt into one record per call and
//! leave for the socket at the writer's flush (or once a full record's worth waits), so that
//! what a writer writes together — a burst of WebSocket messages — is one system call and one
//! wake-up of the peer, not one each; what the socket does not take is kept (up to
//! [`WRITE_BACKLOG`], then the writer waits). A peer that ends the connection without TLS's
//! close_notify is an `UnexpectedEof` error, as with rustls's own reader.

use std::future::poll_fn;
use std::io;
use std::pin::Pin;
use std::sync::{Arc, PoisonError, RwLock};
use std::task::{ready, Context, Poll};

use rustls::server::UnbufferedServerConnection;
use rustls::unbuffered::{
    AppDataRecord, ConnectionState, EncodeError, EncryptError, UnbufferedStatus,
};
use rustls::{HandshakeKind, ServerConfig};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

/// Bytes read from the socket at a time (a record may need more: then as much as it needs).
const READ_SIZE: usize = 4096;

/// Encrypted bytes a writer may leave queued while the socket takes no more; beyond this,
/// writes wait (a peer that stops reading does not make the portal buffer without end).
pub const WRITE_BACKLOG: usize = 64 * 1024;

/// The largest plaintext of one TLS record (RFC 8446 §5.1).
const MAX_FRAGMENT: usize = 16 * 1024;

/// The largest TLS record on the wire: header and ciphertext (RFC 5246 §6.2.3; a peer that
/// announces more is refused by rustls, not read into memory).
const MAX_RECORD: usize = 5 + MAX_FRAGMENT + 2048;

/// Accepts TLS connections with a server configuration that can be replaced while it serves
/// (a renewed certificate): clones share it.
#[derive(Clone)]
pub struct Acceptor {
    config: Arc<RwLock<Arc<ServerConfig>>>,
}

impl Acceptor {
    /// An acceptor for `config`.
    pub fn new(config: Arc<ServerConfig>) -> Acceptor {
        Acceptor {
            config: Arc::new(RwLock::new(config)),
        }
    }

    /// The configuration handshakes begin with now.
    pub fn config(&self) -> Arc<ServerConfig> {
        // A writer that panicked left a whole `Arc` behind: the lock's poison says nothing.
        self.config
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Serve handshakes from now on with `config`; the connections already made keep theirs.
    /// The session cache (TLS 1.2 session IDs, TLS 1.3 stateful tickets) carries over, so a
    /// client resumes across the change as before it.
    pub fn replace(&self, mut config: ServerConfig) {
        let mut current = self.config.write().unwrap_or_else(PoisonError::into_inner);
        config.session_storage = current.session_storage.clone();
        *current = Arc::new(config);
    }

    /// Complete the server side of a handshake on `io` (bound its time with a timeout: a peer
    /// that says nothing keeps it waiting).
    pub async fn accept<IO: Transport>(&self, io: IO) -> io::Result<ServerStream<IO>> {
        let conn = UnbufferedServerConnection::new(self.config()).map_err(tls_error)?;
        let mut stream = ServerStream {
            io,
            conn,
            incoming: Vec::new(),
            plaintext: Vec::new(),
            read: 0,
            outgoing: Vec::new(),
            written: 0,
            peer_closed: false,
            sent_close_notify: false,
        };
        let mut looked_behind = false;
        poll_fn(|cx| stream.poll_handshake(cx, &mut looked_behind)).await?;
        Ok(stream)
    }
}

/// What [`Acceptor::accept`] runs over: a byte stream that can tell, without reading or
/// waiting, whether its peer has closed it.
pub trait Transport: AsyncRead + AsyncWrite + Unpin {
    /// Whether the peer's end of stream (or a reset) is what a read would find next: looked at,
    /// not consumed. `false` where the transport cannot tell (the default).
    fn closed_by_peer(&self) -> bool {
        false
    }
}

/// A look with `MSG_PEEK` (one system call; the socket is non-blocking, so it does not wait):
/// nothing to read but the FIN is 0 bytes, a reset is an error. tokio's readiness cannot say
/// it: a short read clears it, though the FIN came in the same segment as the data.
impl Transport for tokio::net::TcpStream {
    fn closed_by_peer(&self) -> bool {
        let mut byte = [std::mem::MaybeUninit::uninit()];
        match socket2::SockRef::from(self).peek(&mut byte) {
            Ok(n) => n == 0,
            Err(e) => e.kind() != io::ErrorKind::WouldBlock,
        }
    }
}

/// An in-memory pipe (tests): cannot tell.
impl Transport for tokio::io::DuplexStream {}

/// Whether [`Acceptor::accept`] failed because the peer had closed the connection before its
/// first flight was answered: no handshake work was spent on it (a storm's clients that gave up
/// while their connections waited to be accepted).
pub fn abandoned(e: &io::Error) -> bool {
    e.get_ref().is_some_and(|inner| inner.is::<Abandoned>())
}

/// The peer closed (or reset) the connection behind its ClientHello.
#[derive(Debug, thiserror::Error)]
#[error("the TLS peer closed the connection before its ClientHello was answered")]
struct Abandoned;

/// A TLS connection accepted by [`Acceptor::accept`]: `AsyncRead` and `AsyncWrite` of the
/// plaintext.
pub struct ServerStream<IO> {
    io: IO,
    conn: UnbufferedServerConnection,
    /// TLS bytes read and not yet processed (a record's beginning); no allocation when empty.
    incoming: Vec<u8>,
    /// Decrypted bytes the reader has not taken yet: `plaintext[read..]`.
    plaintext: Vec<u8>,
    read: usize,
    /// Records not yet written to the socket: `outgoing[written..]`.
    outgoing: Vec<u8>,
    written: usize,
    /// The peer's close_notify came: after the plaintext before it, reads see the end.
    peer_closed: bool,
    sent_close_notify: bool,
}

impl<IO> ServerStream<IO> {
    /// Whether the handshake was a full one or resumed a session (for the portal's counts).
    pub fn handshake_kind(&self) -> Option<HandshakeKind> {
        self.conn.handshake_kind()
    }

    /// Bytes this stream holds allocated for TLS records and plaintext in transit (0 while the
    /// connection is idle).
    pub fn buffered(&self) -> usize {
        self.incoming.capacity() + self.plaintext.capacity() + self.outgoing.capacity()
    }
}

impl<IO: Transport> ServerStream<IO> {
    /// Drive the handshake: the flights go out while the peer's are read (neither waits for the
    /// other). What follows the handshake (the session ticket) goes out with the first read or
    /// write: a peer that reads nothing until its own handshake is done must not hold it up.
    ///
    /// Before the peer's first flight is answered — a key agreement, and for a full handshake
    /// a signature: most of what a connection costs the portal — the transport looks behind it
    /// ([`Transport::closed_by_peer`]). A client that gave up while its connection waited in the
    /// listen queue or for a worker (a reconnect storm on a busy machine) has closed it, and its
    /// end of stream is already there: the connection is dropped unanswered ([`abandoned`]).
    fn poll_handshake(
        &mut self,
        cx: &mut Context<'_>,
        looked_behind: &mut bool,
    ) -> Poll<io::Result<()>> {
        loop {
            self.process(None)?;
            let _ = self.poll_write_out(cx)?;
            if !self.conn.is_handshaking() {
                return Poll::Ready(Ok(()));
            }
            if self.peer_closed {
                return Poll::Ready(Err(io::Error::new(
                    io::ErrorKind::UnexpectedEof,
                    "TLS peer closed during the handshake",
                )));
            }
            if ready!(self.poll_read_in(cx))? == 0 {
                return Poll::Ready(Err(eof()));
            }
            if !*looked_behind {
                *looked_behind = true;
                if self.io.closed_by_peer() {
                    return Poll::Ready(Err(io::Error::new(
                        io::ErrorKind::ConnectionAborted,
                        Abandoned,
                    )));
                }
            }
        }
    }
}

impl<IO> ServerStream<IO>
where
    IO: AsyncRead + AsyncWrite + Unpin,
{
    /// Read from the socket into `incoming` (as much as the record being received needs, at
    /// least [`READ_SIZE`]); the number of bytes, 0 at the end of the stream.
    fn poll_read_in(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<usize>> {
        let want = record_len(&self.incoming)
            .map_or(READ_SIZE, |len| {
                len.min(MAX_RECORD).saturating_sub(self.incoming.len())
            })
            .max(READ_SIZE);
        if self.incoming.capacity() == 0 {
            self.incoming = spare::take();
        }
        self.incoming.reserve(want);
        let filled = self.incoming.len();
        let spare = self.incoming.spare_capacity_mut();
        let mut buf = ReadBuf::uninit(&mut spare[..want]);
        let polled = Pin::new(&mut self.io).poll_read(cx, &mut buf);
        let n = buf.filled().len();
        // SAFETY: `poll_read` initialised the first `n` bytes of the spare capacity.
        unsafe { self.incoming.set_len(filled + n) };
        if self.incoming.is_empty() {
            spare::give_back(std::mem::take(&mut self.incoming));
        }
        ready!(polled)?;
        Poll::Ready(Ok(n))
    }

    /// Write queued records until none is left or the socket takes no more.
    fn poll_write_out(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        while self.written < self.outgoing.len() {
            let n = ready!(Pin::new(&mut self.io).poll_write(cx, &self.outgoing[self.written..]))?;
            if n == 0 {
                return Poll::Ready(Err(io::ErrorKind::WriteZero.into()));
            }
            self.written += n;
        }
        spare::give_back(std::mem::take(&mut self.outgoing));
        self.written = 0;
        Poll::Ready(Ok(()))
    }

    /// Run the complete records received so far through rustls: handshake messages are
    /// answered into `outgoing`, application data goes into `dest` as far as it fits and the
    /// rest into `plaintext`.
    fn process(&mut self, mut dest: Option<&mut ReadBuf<'_>>) -> io::Result<()> {
        while let Step::More = self.step(&mut dest, Outgoing::Nothing)? {}
        if self.incoming.is_empty() {
            spare::give_back(std::mem::take(&mut self.incoming));
        }
        Ok(())
    }

    /// Queue `send` (once rustls is ready for application data, after whatever came first).
    fn send(&mut self, send: Outgoing<'_>) -> io::Result<()> {
        loop {
            match self.step(&mut None, send)? {
                Step::More => {}
                Step::Sent => return Ok(()),
                Step::Closed => {
                    return Err(io::Error::new(
                        io::ErrorKind::BrokenPipe,
                        "the TLS connection is closed",
                    ))
                }
                Step::Waiting => return Err(tls_error("TLS is not ready for application data")),
            }
        }
    }

    /// One state of rustls, handled whole: records read, handshake data encoded, `send` done
    /// when rustls is ready for application data.
    fn step(
        &mut self,
        dest: &mut Option<&mut ReadBuf<'_>>,
        send: Outgoing<'_>,
    ) -> io::Result<Step> {
        let UnbufferedStatus { mut discard, state } =
            self.conn.process_tls_records(&mut self.incoming);
        let state = match state {
            Ok(state) => state,
            Err(e) => {
                self.incoming.drain(..discard);
                self.queue_alert();
                return Err(tls_error(e));
            }
        };
        let step = match state {
            ConnectionState::ReadTraffic(mut traffic) => {
                while let Some(record) = traffic.next_record() {
                    let AppDataRecord {
                        discard: d,
                        payload,
                    } = record.map_err(tls_error)?;
                    discard += d;
                    deliver(payload, dest, &mut self.plaintext);
                }
                Step::More
            }
            // The configurations made here take no early data (`max_early_data_size` 0).
            ConnectionState::ReadEarlyData(_) => {
                return Err(tls_error("TLS early data is not accepted"));
            }
            ConnectionState::EncodeTlsData(mut encode) => {
                append(&mut self.outgoing, |out| encoded(encode.encode(out)))
                    .map_err(|()| tls_error("a handshake record could not be encoded"))?;
                Step::More
            }
            // Queued in `outgoing` in order: written before anything queued later.
            ConnectionState::TransmitTlsData(transmit) => {
                transmit.done();
                Step::More
            }
            ConnectionState::PeerClosed => {
                self.peer_closed = true;
                Step::More
            }
            ConnectionState::Closed => {
                self.peer_closed = true;
                Step::Closed
            }
            ConnectionState::WriteTraffic(mut traffic) => match send {
                Outgoing::Nothing => Step::Waiting,
                // rustls puts what it queued first (a KeyUpdate answering the peer's) before
                // the sealed records.
                Outgoing::Data(data) => {
                    append(&mut self.outgoing, |out| {
                        encrypted(traffic.encrypt(data, out))
                    })
                    .map_err(|()| tls_error("the connection's keys are exhausted"))?;
                    Step::Sent
                }
                Outgoing::CloseNotify => {
                    append(&mut self.outgoing, |out| {
                        encrypted(traffic.queue_close_notify(out))
                    })
                    .map_err(|()| tls_error("close_notify could not be encrypted"))?;
                    Step::Sent
                }
            },
            // The handshake waits for the peer.
            _ => Step::Waiting,
        };
        self.incoming.drain(..discard);
        Ok(step)
    }

    /// After a TLS error: queue the alert rustls prepared and try to write it now. The alert is
    /// the one record rustls queued in the failing call (what came before went out with the
    /// steps before), so rustls is asked once: a second call would go on to the records again —
    /// a record that could not be deframed would be refused a second time (a second fatal alert:
    /// rustls asserts there is none), and with an empty slice instead of the records it has not
    /// discarded, its handshake deframer reads positions that are gone (a panic inside rustls).
    fn queue_alert(&mut self) {
        let UnbufferedStatus { state, .. } = self.conn.process_tls_records(&mut self.incoming);
        if let Ok(ConnectionState::EncodeTlsData(mut encode)) = state {
            let _ = append(&mut self.outgoing, |out| encoded(encode.encode(out)));
        }
        let mut cx = Context::from_waker(std::task::Waker::noop());
        let _ = self.poll_write_out(&mut cx);
    }
}

/// What a step does once rustls is ready for application data.
#[derive(Clone, Copy)]
enum Outgoing<'a> {
    Nothing,
    Data(&'a [u8]),
    CloseNotify,
}

/// Where a step left the connection.
enum Step {
    /// Something was handled; there may be more.
    More,
    /// The application data or close_notify is queued.
    Sent,
    /// Nothing more until the peer sends something.
    Waiting,
    /// Closed both ways.
    Closed,
}

fn encoded(result: Result<usize, EncodeError>) -> Result<usize, Option<usize>> {
    match result {
        Ok(n) => Ok(n),
        Err(EncodeError::InsufficientSize(s)) => Err(Some(s.required_size)),
        Err(_) => Err(None),
    }
}

fn encrypted(result: Result<usize, EncryptError>) -> Result<usize, Option<usize>> {
    match result {
        Ok(n) => Ok(n),
        Err(EncryptError::InsufficientSize(s)) => Err(Some(s.required_size)),
        Err(_) => Err(None),
    }
}

impl<IO> AsyncRead for ServerStream<IO>
where
    IO: AsyncRead + AsyncWrite + Unpin,
{
    fn poll_read(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        loop {
            if this.read < this.plaintext.len() {
                let n = buf.remaining().min(this.plaintext.len() - this.read);
                buf.put_slice(&this.plaintext[this.read..this.read + n]);
                this.read += n;
                if this.read == this.plaintext.len() {
                    spare::give_back(std::mem::take(&mut this.plaintext));
                    this.read = 0;
                }
                return Poll::Ready(Ok(()));
            }
            if this.peer_closed || buf.remaining() == 0 {
                return Poll::Ready(Ok(()));
            }
            // A handshake message's answer (a key update) goes out as soon as the socket
            // takes it; reading does not wait for it.
            if let Poll::Ready(Err(e)) = this.poll_write_out(cx) {
                return Poll::Ready(Err(e));
            }
            if ready!(this.poll_read_in(cx))? == 0 {
                return Poll::Ready(Err(eof()));
            }
            let before = buf.filled().len();
            this.process(Some(buf))?;
            if buf.filled().len() > before {
                return Poll::Ready(Ok(()));
            }
        }
    }
}

impl<IO> AsyncWrite for ServerStream<IO>
where
    IO: AsyncRead + AsyncWrite + Unpin,
{
    fn poll_write(
        self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        data: &[u8],
    ) -> Poll<io::Result<usize>> {
        let this = self.get_mut();
        if data.is_empty() {
            return Poll::Ready(Ok(0));
        }
        if this.outgoing.len() - this.written >= WRITE_BACKLOG {
            ready!(this.poll_write_out(cx))?;
        }
        let n = data.len().min(MAX_FRAGMENT);
        this.send(Outgoing::Data(&data[..n]))?;
        // Records wait for the flush unless a full record's worth does; what the socket does
        // not take now waits in `outgoing`.
        if this.outgoing.len() - this.written >= MAX_FRAGMENT {
            if let Poll::Ready(Err(e)) = this.poll_write_out(cx) {
                return Poll::Ready(Err(e));
            }
        }
        Poll::Ready(Ok(n))
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        ready!(this.poll_write_out(cx))?;
        Pin::new(&mut this.io).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        if !this.sent_close_notify {
            // Once: a connection closed both ways, or broken, has nothing to say any more.
            this.sent_close_notify = true;
            let _ = this.send(Outgoing::CloseNotify);
        }
        ready!(this.poll_write_out(cx))?;
        match ready!(Pin::new(&mut this.io).poll_shutdown(cx)) {
            // A peer that is gone already is closed enough.
            Err(e) if e.kind() != io::ErrorKind::NotConnected => Poll::Ready(Err(e)),
            _ => Poll::Ready(Ok(())),
        }
    }
}

/// Copy `payload` into `dest` as far as it fits, the rest to the end of `rest`.
fn deliver(payload: &[u8], dest: &mut Option<&mut ReadBuf<'_>>, rest: &mut Vec<u8>) {
    let n = match dest {
        Some(buf) if rest.is_empty() => {
            let n = buf.remaining().min(payload.len());
            buf.put_slice(&payload[..n]);
            n
        }
        _ => 0,
    };
    if n < payload.len() {
        if rest.capacity() == 0 {
            *rest = spare::take();
        }
        rest.extend_from_slice(&payload[n..]);
    }
}

/// A few buffers per thread for the connections that need one next: a connection gives its
/// buffers back as soon as they are empty, and without this every message would allocate and
/// free them again (and so would every read attempt that finds nothing).
mod spare {
    use std::cell::RefCell;

    /// Buffers kept per thread.
    const KEEP: usize = 4;
    /// Buffers larger than this are freed, not kept (one record and its header fit).
    const LARGEST: usize = 2 * super::MAX_RECORD;

    thread_local! {
        static SPARE: RefCell<Vec<Vec<u8>>> = const { RefCell::new(Vec::new()) };
    }

    /// An empty buffer, with room if the thread kept one.
    pub(super) fn take() -> Vec<u8> {
        SPARE.with(|spare| spare.borrow_mut().pop().unwrap_or_default())
    }

    /// Keep `buffer` (emptied) for the next `take` on this thread, if there is room.
    pub(super) fn give_back(mut buffer: Vec<u8>) {
        if buffer.capacity() == 0 || buffer.capacity() > LARGEST {
            return;
        }
        buffer.clear();
        SPARE.with(|spare| {
            let mut spare = spare.borrow_mut();
            if spare.len() < KEEP {
                spare.push(buffer);
            }
        });
    }
}

/// Append what `write` puts into a slice to `out`; `write` answers `Err(Some(size))` when it
/// needs `size` bytes, `Err(None)` when it cannot write at all.
fn append(
    out: &mut Vec<u8>,
    mut write: impl FnMut(&mut [u8]) -> Result<usize, Option<usize>>,
) -> Result<(), ()> {
    let start = out.len();
    let mut room = 256;
    loop {
        out.resize(start + room, 0);
        match write(&mut out[start..]) {
            Ok(n) => {
                out.truncate(start + n);
                return Ok(());
            }
            Err(Some(needed)) if needed > room => room = needed,
            Err(_) => {
                out.truncate(start);
                return Err(());
            }
        }
    }
}

/// The length of the TLS record at the start of `bytes` (header included), once its header
/// is there.
fn record_len(bytes: &[u8]) -> Option<usize> {
    let header = bytes.get(..5)?;
    Some(5 + usize::from(u16::from_be_bytes([header[3], header[4]])))
}

fn tls_error(e: impl Into<Box<dyn std::error::Error + Send + Sync>>) -> io::Error {
    io::Error::new(io::ErrorKind::InvalidData, e)
}

fn eof() -> io::Error {
    io::Error::new(
        io::ErrorKind::UnexpectedEof,
        "peer closed connection without sending TLS close_notify",
    )
}
