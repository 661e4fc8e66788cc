//! `canlift hub`: a virtual CAN bus that speaks socketcand's raw mode over TCP.
//!
//! Every channel name is its own bus. Clients are anything that speaks socketcand: canlift's own
//! `socketcand://` backend, python-can's `socketcand` interface (and so python-canopen), or
//! socketcand's own tools. The dialect follows docs/ARCHITECTURE.md §Conventions: `< hi >` and every `< ok >` are
//! written alone, frames are held back briefly after the raw-mode `< ok >` (python-can reads the
//! `< ok >` with one `recv` and compares it exactly), senders do not get their own frames back,
//! and nothing but frames and `< echo >` is ever written in raw mode.
//!
//! Robustness: each client has a bounded outgoing queue; a client that stops reading is
//! disconnected when it fills. Garbage, invalid identifiers, DLC > 8 and unsupported commands
//! are dropped with a log line; an oversized message disconnects that client. None of it
//! touches the other clients.
//!
//! With a bit rate, frames take their real wire time and arbitrate by CAN-ID (see
//! [`crate::wire`]).

mod arbiter;
mod channel;

use std::collections::HashMap;
use std::future::Future;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::tcp::{OwnedReadHalf, OwnedWriteHalf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, watch, Notify, Semaphore};
use tokio::task::JoinSet;

use self::channel::{Channel, Outgoing, Subscriber};
use crate::socketcand::codec::{self, DecodeError, Decoder, Message};

/// How a hub runs.
#[derive(Debug, Clone)]
pub struct HubConfig {
    /// Where to listen (default 127.0.0.1:29536).
    pub listen: SocketAddr,
    /// Bus bit rate in bit/s; `None` delivers frames as fast as the host can.
    pub bitrate: Option<u32>,
    /// Frames queued for one client before it counts as not reading and is disconnected
    /// (about 48 bytes each, so the default bounds a client's backlog at ~1.5 MB).
    pub client_queue: usize,
    /// Frames one client may have waiting for the bus in bit-rate mode before the hub stops
    /// reading from its socket (TCP backpressure, like a full controller transmit queue).
    pub client_tx_queue: usize,
    /// Concurrent clients at most; more are refused.
    pub max_clients: usize,
    /// Distinct channels at most.
    pub max_channels: usize,
    /// Time a client has to reach raw mode.
    pub handshake_timeout: Duration,
    /// How long frames are held back after the raw-mode `< ok >`.
    pub raw_mode_hold: Duration,
}

impl Default for HubConfig {
    fn default() -> Self {
        HubConfig {
            listen: SocketAddr::from(([127, 0, 0, 1], crate::SOCKETCAND_DEFAULT_PORT)),
            bitrate: None,
            client_queue: 32_768,
            client_tx_queue: 64,
            max_clients: 1024,
            max_channels: 1024,
            handshake_timeout: Duration::from_secs(30),
            raw_mode_hold: Duration::from_millis(50),
        }
    }
}

/// Counters over the hub's life, for logs, metrics and benchmarks.
#[derive(Debug, Default)]
pub struct HubStats {
    /// Frames received from clients.
    pub frames_in: AtomicU64,
    /// Frames queued to clients.
    pub frames_out: AtomicU64,
    /// Clients disconnected for not reading.
    pub clients_dropped: AtomicU64,
    /// Messages dropped as invalid.
    pub bad_messages: AtomicU64,
    /// Clients currently connected.
    pub clients: AtomicU64,
}

struct HubState {
    config: HubConfig,
    channels: Mutex<HashMap<String, Arc<Channel>>>,
    stats: Arc<HubStats>,
    next_client: AtomicU64,
}

impl HubState {
    /// Subscribe `subscriber` to channel `name`, creating it; under the map lock so that a
    /// channel being removed by its last leaver is never joined.
    fn join(&self, name: &str, subscriber: Subscriber) -> Option<Arc<Channel>> {
        let mut channels = self.channels.lock().unwrap_or_else(PoisonError::into_inner);
        if !channels.contains_key(name) && channels.len() >= self.config.max_channels {
            return None;
        }
        let channel = channels
            .entry(name.to_owned())
            .or_insert_with(|| Channel::new(name, self.config.bitrate, self.stats.clone()))
            .clone();
        channel.add(subscriber);
        Some(channel)
    }

    fn leave(&self, channel: &Channel, client: u64) {
        let mut channels = self.channels.lock().unwrap_or_else(PoisonError::into_inner);
        if channel.remove(client) {
            channels.remove(&channel.name);
        }
    }
}

/// A bound hub, not yet serving.
pub struct Hub {
    listener: TcpListener,
    state: Arc<HubState>,
}

/// A running hub; [`HubHandle::shutdown`] stops it and waits for every client task.
pub struct HubHandle {
    addr: SocketAddr,
    stats: Arc<HubStats>,
    stop: watch::Sender<bool>,
    task: tokio::task::JoinHandle<()>,
}

impl Hub {
    /// Bind the listening socket.
    pub async fn bind(config: HubConfig) -> std::io::Result<Hub> {
        let listener = TcpListener::bind(config.listen).await?;
        Ok(Hub {
            listener,
            state: Arc::new(HubState {
                config,
                channels: Mutex::new(HashMap::new()),
                stats: Arc::new(HubStats::default()),
                next_client: AtomicU64::new(1),
            }),
        })
    }

    /// The address actually bound (useful with port 0).
    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.listener.local_addr()
    }

    /// The hub's counters.
    pub fn stats(&self) -> Arc<HubStats> {
        self.state.stats.clone()
    }

    /// Serve until `shutdown` resolves, then close every client and return.
    pub async fn run(self, shutdown: impl Future<Output = ()>) {
        let (stop_tx, stop_rx) = watch::channel(false);
        let mut clients = JoinSet::new();
        tokio::pin!(shutdown);
        loop {
            tokio::select! {
                _ = &mut shutdown => break,
                accepted = self.listener.accept() => match accepted {
                    Ok((stream, peer)) => {
                        let state = self.state.clone();
                        if state.stats.clients.load(Ordering::Relaxed)
                            >= state.config.max_clients as u64
                        {
                            tracing::warn!(%peer, "too many clients; connection refused");
                            continue;
                        }
                        let stop = stop_rx.clone();
                        clients.spawn(serve_client(stream, peer, state, stop));
                    }
                    Err(e) => {
                        // Out of file descriptors and the like: back off instead of spinning.
                        tracing::warn!(error = %e, "accept failed");
                        tokio::time::sleep(Duration::from_millis(50)).await;
                    }
                },
                Some(_) = clients.join_next(), if !clients.is_empty() => {}
            }
        }
        let _ = stop_tx.send(true);
        while clients.join_next().await.is_some() {}
    }

    /// Run in a background task.
    pub fn spawn(self) -> std::io::Result<HubHandle> {
        let addr = self.local_addr()?;
        let stats = self.stats();
        let (stop, mut stopped) = watch::channel(false);
        let task = tokio::spawn(self.run(async move {
            let _ = stopped.wait_for(|&s| s).await;
        }));
        Ok(HubHandle {
            addr,
            stats,
            stop,
            task,
        })
    }
}

impl HubHandle {
    /// Where the hub listens.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// The hub's counters.
    pub fn stats(&self) -> &HubStats {
        &self.stats
    }

    /// Stop accepting, disconnect every client and wait until all are gone.
    pub async fn shutdown(self) {
        let _ = self.stop.send(true);
        let _ = self.task.await;
    }
}

/// Counts a client's bad messages and keeps the log readable under a flood.
struct BadInput {
    client: u64,
    count: u64,
    stats: Arc<HubStats>,
}

impl BadInput {
    fn report(&mut self, error: &DecodeError) {
        self.count += 1;
        self.stats.bad_messages.fetch_add(1, Ordering::Relaxed);
        if self.count <= 10 || self.count.is_power_of_two() {
            tracing::warn!(client = self.client, total = self.count, error = %error, "dropped bad input");
        }
    }
}

async fn serve_client(
    stream: TcpStream,
    peer: SocketAddr,
    state: Arc<HubState>,
    mut stop: watch::Receiver<bool>,
) {
    let client = state.next_client.fetch_add(1, Ordering::Relaxed);
    state.stats.clients.fetch_add(1, Ordering::Relaxed);
    tracing::info!(client, %peer, "client connected");
    let reason = tokio::select! {
        reason = session(stream, client, &state) => reason,
        _ = stop.wait_for(|&s| s) => "hub shutting down".to_owned(),
    };
    state.stats.clients.fetch_sub(1, Ordering::Relaxed);
    tracing::info!(client, %peer, %reason, "client disconnected");
}

/// A client's session from `< hi >` to the end; returns why it ended.
async fn session(stream: TcpStream, client: u64, state: &HubState) -> String {
    if let Err(e) = stream.set_nodelay(true) {
        return format!("setting TCP_NODELAY failed: {e}");
    }
    let (mut reader, mut writer) = stream.into_split();
    let mut decoder = Decoder::new();
    let mut bad = BadInput {
        client,
        count: 0,
        stats: state.stats.clone(),
    };
    let handshake = tokio::time::timeout(
        state.config.handshake_timeout,
        handshake(&mut reader, &mut writer, &mut decoder, &mut bad),
    );
    let channel_name = match handshake.await {
        Ok(Ok(name)) => name,
        Ok(Err(reason)) => return reason,
        Err(_) => return "did not reach raw mode in time".into(),
    };
    let (tx, rx) = mpsc::channel(state.config.client_queue.max(1));
    let kill = Arc::new(Notify::new());
    let subscriber = Subscriber {
        client,
        tx: tx.clone(),
        kill: kill.clone(),
    };
    let Some(channel) = state.join(&channel_name, subscriber) else {
        let _ = writer.write_all(b"< error too many channels >").await;
        return "channel limit reached".into();
    };
    if let Err(e) = writer.write_all(b"< ok >").await {
        state.leave(&channel, client);
        return format!("write failed: {e}");
    }
    tracing::debug!(client, channel = %channel_name, "raw mode");
    let permits = Arc::new(Semaphore::new(state.config.client_tx_queue.max(1)));
    let reason = tokio::select! {
        r = raw_reader(&mut reader, &mut decoder, client, &channel, &tx, &permits, &mut bad) => r,
        r = raw_writer(&mut writer, rx, state.config.raw_mode_hold) => r,
        _ = kill.notified() => "dropped: not reading (outgoing queue full)".into(),
    };
    state.leave(&channel, client);
    reason
}

/// Greeting, `< open CHANNEL >` and `< rawmode >`; returns the channel name.
async fn handshake(
    reader: &mut OwnedReadHalf,
    writer: &mut OwnedWriteHalf,
    decoder: &mut Decoder,
    bad: &mut BadInput,
) -> Result<String, String> {
    let write = |e: std::io::Error| format!("write failed: {e}");
    writer.write_all(b"< hi >").await.map_err(write)?;
    let mut channel: Option<String> = None;
    let mut buf = [0u8; 1024];
    loop {
        while let Some(message) = decoder.next_message() {
            let reply = match message {
                Ok(Message::Open(name)) if channel.is_none() => {
                    channel = Some(name);
                    "< ok >"
                }
                Ok(Message::Open(_)) => "< error a channel is already open >",
                Ok(Message::RawMode) => match channel.take() {
                    // The `< ok >` is written by the caller once the client is on the bus.
                    Some(name) => return Ok(name),
                    None => "< error open a channel first >",
                },
                Ok(Message::Echo) => "< echo >",
                Ok(Message::BcmMode) => "< ok >",
                Ok(Message::ControlMode | Message::IsoTpMode) => {
                    "< error only raw mode is offered by this hub >"
                }
                Ok(_) => "< error unexpected command >",
                Err(DecodeError::Oversized) => return Err("oversized message".into()),
                Err(e) => {
                    bad.report(&e);
                    "< error invalid command >"
                }
            };
            writer.write_all(reply.as_bytes()).await.map_err(write)?;
        }
        match reader.read(&mut buf).await {
            Ok(0) => return Err("closed by client before raw mode".into()),
            Ok(n) => decoder.feed(&buf[..n]),
            Err(e) => return Err(format!("read failed: {e}")),
        }
    }
}

async fn raw_reader(
    reader: &mut OwnedReadHalf,
    decoder: &mut Decoder,
    client: u64,
    channel: &Channel,
    own_queue: &mpsc::Sender<Outgoing>,
    permits: &Arc<Semaphore>,
    bad: &mut BadInput,
) -> String {
    let mut buf = vec![0u8; 16 * 1024];
    loop {
        while let Some(message) = decoder.next_message() {
            match message {
                Ok(Message::Send(frame)) => {
                    let permit = if channel.is_timed() {
                        match permits.clone().acquire_owned().await {
                            Ok(p) => Some(p),
                            Err(_) => return "hub shutting down".into(),
                        }
                    } else {
                        None
                    };
                    channel.submit(client, frame, permit);
                }
                Ok(Message::Echo) => {
                    if own_queue.try_send(Outgoing::Echo).is_err() {
                        return "dropped: not reading (outgoing queue full)".into();
                    }
                }
                Ok(other) => {
                    tracing::warn!(client, ?other, "command not available in raw mode; dropped")
                }
                Err(DecodeError::Oversized) => return "oversized message".into(),
                Err(e) => bad.report(&e),
            }
        }
        match reader.read(&mut buf).await {
            Ok(0) => return "closed by client".into(),
            Ok(n) => decoder.feed(&buf[..n]),
            Err(e) => return format!("read failed: {e}"),
        }
    }
}

async fn raw_writer(
    writer: &mut OwnedWriteHalf,
    mut rx: mpsc::Receiver<Outgoing>,
    hold: Duration,
) -> String {
    // python-can reads the raw-mode `< ok >` with a single recv and compares it exactly, so
    // nothing may follow it in the same segment: hold frames back (they queue meanwhile).
    tokio::time::sleep(hold).await;
    let mut text = String::with_capacity(64 * 64);
    loop {
        let Some(first) = rx.recv().await else {
            return "hub closed the channel".into();
        };
        text.clear();
        encode(first, &mut text);
        for _ in 1..64 {
            match rx.try_recv() {
                Ok(next) => encode(next, &mut text),
                Err(_) => break,
            }
        }
        if let Err(e) = writer.write_all(text.as_bytes()).await {
            return format!("write failed: {e}");
        }
    }
}

fn encode(out: Outgoing, text: &mut String) {
    match out {
        Outgoing::Frame(frame) => {
            let at = frame.timestamp().unwrap_or_else(std::time::SystemTime::now);
            codec::encode_frame(&frame, at, text);
        }
        Outgoing::Echo => text.push_str("< echo >"),
    }
}
