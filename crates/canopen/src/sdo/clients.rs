//! The async SDO client (feature `tokio`): [`SdoClients`] keeps every node's SDO client channels
//! on one [`canbus::Bus`] — from the dictionary's 0x1280–0x12FF or the default channel — runs
//! the sans-IO [`super::client::SdoClient`] on them, queues transfers per channel and sets a
//! channel that falls silent aside until it answers again; typed and raw reads and writes,
//! progress, and streamed DOMAINs.

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};

use canbus::{Bus, BusEvent, BusSender, CanId, Filter, Frame, Handled};
use tokio::sync::mpsc;

use crate::od::ObjectDictionary;
use crate::sdo::abort::AbortCode;
use crate::sdo::client::{ClientConfig, DownloadSource, SdoClient, SdoError, Transfer};
use crate::sdo::msg::Request;
use crate::sdo::server::default_channel;
use crate::sdo::{payload, Payload};
use crate::types::{CanopenValue, TypeError};

/// The SDO client channels of a dictionary: (server node-ID, request COB-ID, response COB-ID) of
/// every valid SDO client parameter object 0x1280–0x12FF (sub-indices 1, 2 and 3).
pub fn client_channels(od: &ObjectDictionary) -> Vec<(u8, CanId, CanId)> {
    let mut channels = Vec::new();
    for index in 0x1280..=0x12FF {
        let number = |sub| match od.get_value(index, sub) {
            Ok(crate::types::Value::Uint(v)) => u32::try_from(v).ok(),
            _ => None,
        };
        if let (Some(tx), Some(rx), Some(node)) = (number(1), number(2), number(3)) {
            if let (Some(tx), Some(rx), Ok(node)) = (
                crate::cob::id_from_parameter(tx),
                crate::cob::id_from_parameter(rx),
                u8::try_from(node),
            ) {
                channels.push((node, tx, rx));
            }
        }
    }
    channels
}

fn frame(id: CanId, p: &Payload) -> Frame {
    Frame::new(id, p).unwrap_or_else(|_| unreachable!("8 bytes always fit"))
}

/// Why an SDO operation failed, from the caller's point of view.
#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The transfer failed on the protocol level.
    #[error("SDO {index:04X}:{sub:02X} on node {node}: {error}")]
    Sdo {
        /// Node-ID.
        node: u8,
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// What went wrong (part of this error's message, so not chained as its source).
        error: SdoError,
    },
    /// The value read does not fit the requested type.
    #[error("SDO {index:04X}:{sub:02X} on node {node}: {error}")]
    Type {
        /// Node-ID.
        node: u8,
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The mismatch (part of this error's message).
        error: TypeError,
    },
    /// The bus failed.
    #[error(transparent)]
    Bus(#[from] canbus::BusError),
    /// The client or its channel is gone (the bus closed).
    #[error("SDO client closed")]
    Closed,
    /// Writing uploaded data to the caller's sink failed (the transfer was aborted).
    #[error("storing uploaded data failed: {0}")]
    Sink(String),
}

impl ClientError {
    /// The CiA 301 abort code that describes the failure. A bus link that is down (the hub
    /// gone, an interface down) is a timeout to whoever asked: the node cannot answer, as if it
    /// had not (CiA 301 has no abort code of its own for it).
    pub fn abort_code(&self) -> AbortCode {
        match self {
            ClientError::Sdo { error, .. } => error.abort_code(),
            ClientError::Type { error, .. } => error.abort_code(),
            ClientError::Bus(canbus::BusError::Offline { .. }) => AbortCode::TIMEOUT,
            ClientError::Bus(_) | ClientError::Closed => AbortCode::GENERAL,
            ClientError::Sink(_) => AbortCode::CANNOT_STORE,
        }
    }
}

/// Progress of a transfer: bytes done and the total if known.
pub type Progress<'a> = &'a (dyn Fn(u64, Option<u64>) + Send + Sync);

/// Options for one transfer.
#[derive(Clone, Copy)]
pub struct TransferOptions<'a> {
    /// Expedited/segmented or block.
    pub how: Transfer,
    /// Called as the transfer advances.
    pub progress: Option<Progress<'a>>,
    /// This transfer's response timeout instead of the client's (a CiA 309-3 session sets its
    /// own with `set sdo_timeout`).
    pub timeout: Option<Duration>,
}

impl Default for TransferOptions<'_> {
    fn default() -> Self {
        TransferOptions {
            how: Transfer::Normal,
            progress: None,
            timeout: None,
        }
    }
}

struct ClientInner {
    sender: BusSender,
    /// The client's endpoint, its frames routed by [`route`].
    _receiver: Handled,
    config: ClientConfig,
    /// Responses for the transfer in progress, by response COB-ID.
    routes: Routes,
    /// Configured channels (request, response COB-ID) by server node-ID; a node without any
    /// uses its default channel.
    channels: HashMap<u8, Vec<(CanId, CanId)>>,
    /// Each node's channels as they are taken and given back, made at its first transfer.
    nodes: Mutex<HashMap<u8, Arc<NodeChannels>>>,
    /// How often a channel set aside is asked again.
    probe_nanos: AtomicU64,
}

/// Responses for the transfers in progress, by response COB-ID; shared with the bus's delivery.
type Routes = Arc<Mutex<HashMap<CanId, mpsc::Sender<Payload>>>>;

/// Hand a response to the transfer waiting on its COB-ID, if any.
fn route(routes: &Routes, f: &Frame) {
    let Some(p) = payload(f.data()) else { return };
    let routes = routes.lock().unwrap_or_else(PoisonError::into_inner);
    if let Some(route) = routes.get(&f.id()) {
        let _ = route.try_send(p);
    }
}

/// Timeouts in a row on one channel after which it is set aside — each after the first
/// only if the node answered on another channel since the one before.
const SILENT_LIMIT: u32 = 3;

/// The client channels to one node. A channel carries one transfer at a time (CiA 301
/// §7.2.4.3: a server channel serves one client transfer), so a node reached by several
/// channels — further SDO servers 1201h ff. assigned to this client — serves as many transfers
/// at once; the rest wait their turn, first come first served. Free channels are taken in turn
/// (oldest first), so every channel carries transfers even when they come one by one.
///
/// A channel that stops answering while the node answers on another (moved or closed on the
/// node, CiA 301 §7.5.2.33) would fail every transfer that lands on it: after [`SILENT_LIMIT`]
/// timeouts in a row it is set aside — a task holds it, as a transfer would, and asks it
/// again at intervals until it answers — as long as another channel stays in service.
struct NodeChannels {
    /// One permit per channel; the semaphore queues waiters in order.
    permits: tokio::sync::Semaphore,
    /// The channels no transfer holds, and what the node's channels have shown.
    pool: Mutex<Pool>,
    /// All of them, in the configured order.
    all: Vec<(CanId, CanId)>,
    /// Woken when a channel is set aside (a wait for all channels in service waits for one
    /// fewer).
    set_aside: tokio::sync::Notify,
}

#[derive(Default)]
struct Pool {
    free: std::collections::VecDeque<(CanId, CanId)>,
    /// Transfers the node answered, on any of its channels.
    answers: u64,
    /// Per channel (by request COB-ID): timeouts in a row that count, and `answers` at the
    /// last of them.
    silent: HashMap<CanId, (u32, u64)>,
    /// Channels set aside.
    aside: usize,
}

/// What one transfer on a channel showed about it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Heard {
    /// A response (data or an abort): the channel works.
    Answer,
    /// No response in time.
    Silence,
    /// Nothing about the channel (the bus or the caller failed).
    Nothing,
}

impl Heard {
    fn of<T>(result: &Result<T, ClientError>) -> Heard {
        match result {
            Ok(_) => Heard::Answer,
            Err(ClientError::Sdo {
                error: SdoError::Timeout,
                ..
            }) => Heard::Silence,
            Err(ClientError::Sdo { .. } | ClientError::Type { .. }) => Heard::Answer,
            Err(_) => Heard::Nothing,
        }
    }
}

impl NodeChannels {
    fn new(channels: Vec<(CanId, CanId)>) -> Self {
        NodeChannels {
            permits: tokio::sync::Semaphore::new(channels.len()),
            pool: Mutex::new(Pool {
                free: channels.iter().copied().collect(),
                ..Pool::default()
            }),
            all: channels,
            set_aside: tokio::sync::Notify::new(),
        }
    }

    fn pool(&self) -> std::sync::MutexGuard<'_, Pool> {
        self.pool.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Wait for a free channel; it is given back when the returned guard drops.
    async fn take(self: &Arc<Self>) -> Result<ChannelGuard, ClientError> {
        let permit = self
            .permits
            .acquire()
            .await
            .map_err(|_| ClientError::Closed)?;
        self.claim(permit).pop().ok_or(ClientError::Closed)
    }

    /// A free channel for each of the `permits` held: the permits go with the guards, which
    /// give them back with their channels. (There is a free channel per permit; should one be
    /// missing, its permit is released, not lost.)
    fn claim(self: &Arc<Self>, permits: tokio::sync::SemaphorePermit<'_>) -> Vec<ChannelGuard> {
        let count = permits.num_permits();
        permits.forget();
        let mut pool = self.pool();
        let taken: Vec<_> = (0..count).filter_map(|_| pool.free.pop_front()).collect();
        self.permits.add_permits(count - taken.len());
        taken
            .into_iter()
            .map(|channel| ChannelGuard {
                node: self.clone(),
                channel,
            })
            .collect()
    }

    /// Note what a transfer on `channel` showed; whether the channel is to be set aside now.
    fn heard(&self, channel: (CanId, CanId), heard: Heard) -> bool {
        let mut pool = self.pool();
        let answers = pool.answers;
        match heard {
            Heard::Nothing => false,
            Heard::Answer => {
                pool.answers += 1;
                pool.silent.remove(&channel.0);
                false
            }
            Heard::Silence => {
                // A node that answers on no channel (off, booting) is not a channel's fault:
                // after the first, a timeout counts only if the node answered since the last.
                let (count, last) = pool.silent.entry(channel.0).or_insert((0, answers));
                if *count == 0 || answers > *last {
                    *count += 1;
                }
                *last = answers;
                let set_aside = *count >= SILENT_LIMIT && pool.aside + 1 < self.all.len();
                if set_aside {
                    pool.aside += 1;
                    pool.silent.remove(&channel.0);
                }
                set_aside
            }
        }
    }

    /// A channel set aside answers again.
    fn back_in_service(&self) {
        let mut pool = self.pool();
        pool.aside = pool.aside.saturating_sub(1);
    }
}

/// A channel held by one transfer (or by the task that asks a channel set aside): given back,
/// with its permit, when this drops — the channel first, so that whoever gets the permit finds
/// a channel.
struct ChannelGuard {
    node: Arc<NodeChannels>,
    channel: (CanId, CanId),
}

impl Drop for ChannelGuard {
    fn drop(&mut self) {
        self.node.pool().free.push_back(self.channel);
        self.node.permits.add_permits(1);
    }
}

/// A transfer under way on a channel the client holds. Dropped before the transfer ends (its
/// caller gave up on it: a timeout around it, a cancelled task), it aborts the transfer on the
/// bus with 08000000h — either side may abort (CiA 301 §7.2.4.3.17) — so that the node's server
/// does not wait for the rest until its own timeout and refuse the next transfer's request on
/// the channel as out of place (05040001h); and it gives the channel back only once the abort
/// is sent and the channel has fallen quiet (see [`QUIET`]), so that neither the next
/// transfer's request goes out before the abort nor an answer meant for this transfer reaches
/// the next one.
struct UnderWay {
    /// The channel and its route, until the transfer ends.
    held: Option<(ChannelGuard, Route)>,
    object: (u16, u8),
    sender: BusSender,
    /// The transfer's response timeout: how long its node may take to answer.
    timeout: Duration,
}

/// How long a channel whose transfer was given up must stay silent, after a response to it,
/// before the next transfer may use it. The node answers what the transfer last asked before
/// it reads the abort (a server serves its channel's requests in order), and in a block upload
/// may still be sending a sub-block's segments: a response that came late to the transfer it
/// answers would be taken by the next transfer on the channel for its own, and fail it
/// (05040001h). Frames of one answer follow each other within a millisecond or two, on a bus
/// or through socketcand.
const QUIET: Duration = Duration::from_millis(10);

impl UnderWay {
    /// The transfer ended (done or failed): the channel, nothing to abort.
    fn ended(mut self) -> Option<ChannelGuard> {
        self.held.take().map(|(turn, _)| turn)
    }
}

impl Drop for UnderWay {
    fn drop(&mut self) {
        let Some((turn, mut route)) = self.held.take() else {
            return;
        };
        // Outside a runtime (it is shutting down) nothing can be sent: the server times out.
        let Ok(runtime) = tokio::runtime::Handle::try_current() else {
            return;
        };
        let (index, sub) = self.object;
        let code = AbortCode::GENERAL;
        let abort = frame(
            route.channel.0,
            &Request::Abort { index, sub, code }.write(),
        );
        let sender = self.sender.clone();
        let timeout = self.timeout;
        runtime.spawn(async move {
            let _ = sender.send(abort).await;
            // The route still takes the channel's responses, those already queued in it among
            // them. The first may take as long as the node may take to answer: a silent node
            // holds the channel that long once.
            let mut wait = timeout;
            while let Ok(Some(_)) = tokio::time::timeout(wait, route.responses.recv()).await {
                wait = QUIET;
            }
            drop(route);
            drop(turn);
        });
    }
}

/// SDO client for every node of a bus (the default client channels 0x600/0x580 + node-ID, or
/// the channels configured for a node). Transfers to different nodes run concurrently, and to
/// one node as many as it has channels; the others queue.
#[derive(Clone)]
pub struct SdoClients {
    inner: Arc<ClientInner>,
}

impl SdoClients {
    /// Use `bus` for SDO client transfers on the default channels (0x600/0x580 + node-ID);
    /// responses are routed to their transfers as the bus delivers them.
    pub fn new(bus: Bus, config: ClientConfig) -> Self {
        Self::with_channels(bus, config, &[])
    }

    /// Like [`Self::new`], with configured client channels (server node-ID, request COB-ID,
    /// response COB-ID), e.g. from [`client_channels`]; a node may have several, and transfers
    /// to it then run on all of them at once (its default channel only if listed). Other nodes
    /// use their default channel.
    pub fn with_channels(bus: Bus, config: ClientConfig, channels: &[(u8, CanId, CanId)]) -> Self {
        let (sender, mut receiver) = bus.split();
        let mut filters = vec![Filter::standard(0x580, 0x780)];
        filters.extend(
            channels
                .iter()
                .map(|&(_, _, response)| Filter::exact(response)),
        );
        receiver.set_filters(&filters);
        let routes = Routes::default();
        // Responses are routed where the bus delivers them, not by a task of the client's own:
        // one hand-over less between the answer and the transfer waiting for it.
        let receiver = receiver.handle_with({
            let routes = routes.clone();
            move |event| {
                if let BusEvent::Frame(f) = event {
                    route(&routes, &f);
                }
            }
        });
        let inner = Arc::new(ClientInner {
            sender,
            _receiver: receiver,
            config,
            routes,
            channels: channels
                .iter()
                .fold(HashMap::new(), |mut by_node, &(node, req, resp)| {
                    by_node
                        .entry(node)
                        .or_insert_with(Vec::new)
                        .push((req, resp));
                    by_node
                }),
            nodes: Mutex::new(HashMap::new()),
            probe_nanos: AtomicU64::new(10_000_000_000),
        });
        SdoClients { inner }
    }

    fn node_channels(&self, node: u8) -> Arc<NodeChannels> {
        self.inner
            .nodes
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .entry(node)
            .or_insert_with(|| {
                let channels = self
                    .inner
                    .channels
                    .get(&node)
                    .cloned()
                    .unwrap_or_else(|| vec![default_channel(node & 0x7F)]);
                Arc::new(NodeChannels::new(channels))
            })
            .clone()
    }

    /// Read 1000h (the device type, which every CiA 301 device has) on all of `node`'s channels
    /// in service at once, holding them meanwhile (other transfers to the node wait, at most one
    /// response timeout): which ones answer, in the configured order. A channel configured here
    /// that the node does not serve would fail every transfer that lands on it; this finds it.
    /// Channels set aside (see [`Self::set_probe_interval`]) are their probe's, not checked.
    /// A check given up on aborts its reads and holds their channels until quiet, as any
    /// transfer given up on.
    pub async fn check_channels(
        &self,
        node: u8,
    ) -> Result<Vec<((CanId, CanId), Result<(), ClientError>)>, ClientError> {
        let channels = self.node_channels(node);
        let held = loop {
            // One set aside meanwhile would never come back to this wait: count again.
            let aside = channels.set_aside.notified();
            tokio::pin!(aside);
            aside.as_mut().enable();
            let in_service = channels.all.len().saturating_sub(channels.pool().aside);
            let count = u32::try_from(in_service).map_err(|_| ClientError::Closed)?;
            tokio::select! {
                held = channels.permits.acquire_many(count) => {
                    break held.map_err(|_| ClientError::Closed)?;
                }
                () = &mut aside => {}
            }
        };
        let mut reads = tokio::task::JoinSet::new();
        for turn in channels.claim(held) {
            let sdo = self.clone();
            reads.spawn(async move {
                let channel = turn.channel;
                let options = TransferOptions::default();
                let (answer, turn) = sdo
                    .transfer_held(turn, node, (0x1000, 0), None, None, options)
                    .await;
                (channel, answer.map(|_| ()), turn)
            });
        }
        let mut answers = Vec::with_capacity(channels.all.len());
        while let Some(done) = reads.join_next().await {
            answers.push(done.map_err(|_| ClientError::Closed)?);
        }
        answers.sort_by_key(|(channel, ..)| channels.all.iter().position(|c| c == channel));
        // The channels go back in the configured order, whichever read ended first: the
        // transfers after a check take them in that order.
        Ok(answers
            .into_iter()
            .map(|(channel, answer, _turn)| (channel, answer))
            .collect())
    }

    /// How often a channel set aside is asked whether it answers again (default 10 s). A
    /// channel is set aside after three timeouts in a row while its node answers on another of
    /// its channels, as long as another stays in service: transfers then use the others.
    pub fn set_probe_interval(&self, every: Duration) {
        let nanos = u64::try_from(every.as_nanos()).unwrap_or(u64::MAX);
        self.inner.probe_nanos.store(nanos, Ordering::Relaxed);
    }

    /// Run one transfer: a download from `source`, or an upload (into `sink` as it arrives, or
    /// returned at the end).
    async fn transfer(
        &self,
        node: u8,
        object: (u16, u8),
        source: Option<Box<dyn DownloadSource>>,
        sink: Option<&mut (dyn std::io::Write + Send)>,
        options: TransferOptions<'_>,
    ) -> Result<Vec<u8>, ClientError> {
        let channels = self.node_channels(node);
        let turn = channels.take().await?;
        let channel = turn.channel;
        let (result, turn) = self
            .transfer_held(turn, node, object, source, sink, options)
            .await;
        let Some(turn) = turn else {
            return result;
        };
        if channels.heard(channel, Heard::of(&result)) {
            self.set_aside(node, turn);
        }
        result
    }

    /// Run one transfer on `turn`'s channel; the channel back when it ended. A transfer given
    /// up on (its future dropped) is aborted and its channel held until quiet ([`UnderWay`]).
    async fn transfer_held(
        &self,
        turn: ChannelGuard,
        node: u8,
        object: (u16, u8),
        source: Option<Box<dyn DownloadSource>>,
        sink: Option<&mut (dyn std::io::Write + Send)>,
        options: TransferOptions<'_>,
    ) -> (Result<Vec<u8>, ClientError>, Option<ChannelGuard>) {
        let route = Route::open(&self.inner.routes, turn.channel);
        let mut under_way = UnderWay {
            held: Some((turn, route)),
            object,
            sender: self.inner.sender.clone(),
            timeout: options.timeout.unwrap_or(self.inner.config.timeout),
        };
        let result = match &mut under_way.held {
            Some((_, route)) => {
                self.transfer_on(route, node, object, source, sink, options)
                    .await
            }
            None => Err(ClientError::Closed),
        };
        (result, under_way.ended())
    }

    /// Hold `turn`'s channel in a task that asks it (1000h) at every probe interval, until it
    /// answers or the client is gone; then it is free again.
    fn set_aside(&self, node: u8, turn: ChannelGuard) {
        let every = Duration::from_nanos(self.inner.probe_nanos.load(Ordering::Relaxed));
        let (request, response) = turn.channel;
        tracing::warn!(
            node,
            %request,
            %response,
            "SDO channel set aside: {SILENT_LIMIT} timeouts in a row while the node answers on \
             its other channels (moved or closed on the node?); asked again every {every:?}"
        );
        turn.node.set_aside.notify_waiters();
        let client = Arc::downgrade(&self.inner);
        tokio::spawn(async move {
            loop {
                tokio::time::sleep(every).await;
                let Some(inner) = client.upgrade() else {
                    return;
                };
                let sdo = SdoClients { inner };
                let options = TransferOptions::default();
                let mut route = Route::open(&sdo.inner.routes, turn.channel);
                let answer = sdo
                    .transfer_on(&mut route, node, (0x1000, 0), None, None, options)
                    .await;
                if Heard::of(&answer) == Heard::Answer {
                    turn.node.back_in_service();
                    tracing::info!(node, %request, "SDO channel answers again: back in service");
                    return;
                }
            }
        });
    }

    /// [`Self::transfer`] on `channel`, which the caller holds.
    async fn transfer_on(
        &self,
        route: &mut Route,
        node: u8,
        (index, sub): (u16, u8),
        source: Option<Box<dyn DownloadSource>>,
        mut sink: Option<&mut (dyn std::io::Write + Send)>,
        options: TransferOptions<'_>,
    ) -> Result<Vec<u8>, ClientError> {
        let request_id = route.channel.0;
        let rx = &mut route.responses;
        let mut config = self.inner.config.clone();
        if let Some(timeout) = options.timeout {
            config.timeout = timeout;
        }
        let mut client = SdoClient::new(config);
        let mut out = Vec::new();
        let now = Instant::now();
        let wrap = |error| ClientError::Sdo {
            node,
            index,
            sub,
            error,
        };
        match source {
            Some(source) => {
                client.start_download_from(index, sub, source, options.how, now, &mut out)
            }
            None => client.start_upload(index, sub, options.how, now, &mut out),
        }
        .map_err(wrap)?;
        let streaming = sink.is_some();
        let mut drain =
            |client: &mut SdoClient, rest: Option<Vec<u8>>| -> Result<(), ClientError> {
                if let Some(sink) = sink.as_mut() {
                    let chunk = rest.unwrap_or_else(|| client.take_received());
                    sink.write_all(&chunk)
                        .map_err(|e| ClientError::Sink(e.to_string()))?;
                }
                Ok(())
            };
        loop {
            for p in out.drain(..) {
                self.inner.sender.send(frame(request_id, &p)).await?;
            }
            let deadline = client
                .poll_timeout()
                .unwrap_or_else(|| Instant::now() + Duration::from_secs(1));
            let outcome = tokio::select! {
                p = rx.recv() => match p {
                    Some(p) => client.handle(&p, Instant::now(), &mut out),
                    None => return Err(ClientError::Closed),
                },
                _ = tokio::time::sleep_until(deadline.into()) => client.handle_timeout(Instant::now(), &mut out),
            };
            if let Some(progress) = options.progress {
                let (done, total) = client.progress();
                progress(done, total);
            }
            match outcome {
                None => {
                    if let Err(e) = drain(&mut client, None) {
                        client.abort(AbortCode::CANNOT_STORE, &mut out);
                        for p in out.drain(..) {
                            self.inner.sender.send(frame(request_id, &p)).await?;
                        }
                        return Err(e);
                    }
                }
                Some(outcome) => {
                    for p in out.drain(..) {
                        self.inner.sender.send(frame(request_id, &p)).await?;
                    }
                    let data = outcome.map_err(wrap)?;
                    if streaming {
                        drain(&mut client, Some(data))?;
                        return Ok(Vec::new());
                    }
                    return Ok(data);
                }
            }
        }
    }

    /// Read a value of any size into `sink` as it arrives (a large DOMAIN never sits in
    /// memory); returns the bytes written.
    pub async fn read_to(
        &self,
        node: u8,
        index: u16,
        sub: u8,
        sink: &mut (dyn std::io::Write + Send),
        options: TransferOptions<'_>,
    ) -> Result<u64, ClientError> {
        let mut counter = CountingWriter {
            inner: sink,
            count: 0,
        };
        self.transfer(node, (index, sub), None, Some(&mut counter), options)
            .await?;
        Ok(counter.count)
    }

    /// Write the bytes of `source` (e.g. a [`crate::sdo::client::FileSource`]), reading them as
    /// the transfer advances.
    pub async fn write_from(
        &self,
        node: u8,
        index: u16,
        sub: u8,
        source: Box<dyn DownloadSource>,
        options: TransferOptions<'_>,
    ) -> Result<(), ClientError> {
        self.transfer(node, (index, sub), Some(source), None, options)
            .await
            .map(drop)
    }

    /// Wait until every frame of finished transfers has left this process (see
    /// [`canbus::BusSender::flush`]): call it before exiting.
    pub async fn flush(&self) -> Result<(), ClientError> {
        Ok(self.inner.sender.flush().await?)
    }

    /// Read raw bytes from `node`.
    pub async fn read_raw(&self, node: u8, index: u16, sub: u8) -> Result<Vec<u8>, ClientError> {
        self.transfer(node, (index, sub), None, None, TransferOptions::default())
            .await
    }

    /// Read raw bytes with options (block transfer, progress).
    pub async fn read_with(
        &self,
        node: u8,
        index: u16,
        sub: u8,
        options: TransferOptions<'_>,
    ) -> Result<Vec<u8>, ClientError> {
        self.transfer(node, (index, sub), None, None, options).await
    }

    /// Read a typed value: `read::<u32>(1, 0x1000, 0)`.
    pub async fn read<T: CanopenValue>(
        &self,
        node: u8,
        index: u16,
        sub: u8,
    ) -> Result<T, ClientError> {
        let bytes = self.read_raw(node, index, sub).await?;
        T::from_bytes(&bytes).map_err(|error| ClientError::Type {
            node,
            index,
            sub,
            error,
        })
    }

    /// Write raw bytes to `node`.
    pub async fn write_raw(
        &self,
        node: u8,
        index: u16,
        sub: u8,
        data: &[u8],
    ) -> Result<(), ClientError> {
        self.transfer(
            node,
            (index, sub),
            Some(Box::new(data.to_vec())),
            None,
            TransferOptions::default(),
        )
        .await
        .map(drop)
    }

    /// Write raw bytes with options (block transfer, progress).
    pub async fn write_with(
        &self,
        node: u8,
        index: u16,
        sub: u8,
        data: Vec<u8>,
        options: TransferOptions<'_>,
    ) -> Result<(), ClientError> {
        self.transfer(node, (index, sub), Some(Box::new(data)), None, options)
            .await
            .map(drop)
    }

    /// Write a typed value: `write(1, 0x1017, 0, 1000u16)`.
    pub async fn write<T: CanopenValue>(
        &self,
        node: u8,
        index: u16,
        sub: u8,
        value: T,
    ) -> Result<(), ClientError> {
        self.write_raw(node, index, sub, &value.to_bytes()).await
    }
}

/// Counts what passes through to the caller's sink.
struct CountingWriter<'a> {
    inner: &'a mut (dyn std::io::Write + Send),
    count: u64,
}

impl std::io::Write for CountingWriter<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.count += n as u64;
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// A channel held by a transfer: the request COB-ID it sends on, and the responses on its
/// response COB-ID, routed here until this drops.
struct Route {
    routes: Routes,
    channel: (CanId, CanId),
    responses: mpsc::Receiver<Payload>,
}

impl Route {
    fn open(routes: &Routes, channel: (CanId, CanId)) -> Route {
        let (tx, responses) = mpsc::channel(256);
        routes
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(channel.1, tx);
        Route {
            routes: routes.clone(),
            channel,
            responses,
        }
    }
}

impl Drop for Route {
    fn drop(&mut self) {
        self.routes
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .remove(&self.channel.1);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::od::{Access, Object, SharedDictionary, Variable};
    use crate::sdo::serve::serve_sdo;
    use crate::sdo::server::ServerConfig;
    use crate::types::{DataType, Value};
    use canbus::BusOptions;
    use tokio::task::JoinHandle;

    fn node_dictionary(serial: u32) -> SharedDictionary {
        let mut od = ObjectDictionary::new();
        od.insert(Object::var(
            0x1000,
            Variable::new("Device type", DataType::Unsigned32, Access::Ro)
                .with_value(Value::Uint(0x0001_01A1)),
        ));
        od.insert(Object::var(
            0x1018,
            Variable::new("Serial", DataType::Unsigned32, Access::Ro)
                .with_value(Value::Uint(serial.into())),
        ));
        od.insert(Object::var(
            0x2000,
            Variable::new("Blob", DataType::Domain, Access::Rw),
        ));
        Arc::new(Mutex::new(od))
    }

    /// A client dropped while the bus delivers answers to it: the bus goes on. (Its answers
    /// were once routed through a `Weak` to the client, upgraded in the delivery: when that
    /// was the last reference, the client's drop waited for the delivery it was part of.)
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_client_dropped_while_answers_arrive_leaves_the_bus_working() {
        let url = "mem://sdo-clients-dropped";
        let flooder = Bus::open(url).await.unwrap();
        let mut witness = Bus::open(url).await.unwrap();
        witness
            .receiver
            .set_filters(&[Filter::exact(CanId::Standard(0x100))]);
        let flooding = Arc::new(std::sync::atomic::AtomicBool::new(true));
        let flood = {
            let flooding = flooding.clone();
            let answer = Frame::standard(0x585, &[0x43, 0, 0x10, 0, 1, 2, 3, 4]).unwrap();
            std::thread::spawn(move || {
                let rt = tokio::runtime::Builder::new_current_thread()
                    .build()
                    .unwrap();
                while flooding.load(std::sync::atomic::Ordering::Relaxed) {
                    rt.block_on(flooder.send(answer)).unwrap();
                }
                flooder
            })
        };
        for _ in 0..2000 {
            let sdo = SdoClients::new(Bus::open(url).await.unwrap(), ClientConfig::default());
            tokio::task::yield_now().await;
            drop(sdo);
        }
        flooding.store(false, std::sync::atomic::Ordering::Relaxed);
        let (done, joined) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let _ = done.send(flood.join().is_ok());
        });
        assert_eq!(
            joined.recv_timeout(Duration::from_secs(10)),
            Ok(true),
            "the bus's delivery hung"
        );
        let probe = Bus::open(url).await.unwrap();
        probe
            .send(Frame::standard(0x100, &[1]).unwrap())
            .await
            .unwrap();
        let seen = tokio::time::timeout(Duration::from_secs(5), witness.receiver.recv_frame())
            .await
            .expect("the bus delivers")
            .unwrap();
        assert_eq!(seen.id(), CanId::Standard(0x100));
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn typed_and_raw_transfers_over_a_bus() {
        let url = "mem://sdo-clients-typed";
        let od = node_dictionary(7);
        let server = serve_sdo(
            Bus::open(url).await.unwrap(),
            od.clone(),
            5,
            ServerConfig::default(),
        );
        let sdo = SdoClients::new(Bus::open(url).await.unwrap(), ClientConfig::default());
        assert_eq!(sdo.read::<u32>(5, 0x1000, 0).await.unwrap(), 0x0001_01A1);
        let err = sdo.read::<u16>(5, 0x1000, 0).await.unwrap_err();
        assert_eq!(err.abort_code(), AbortCode::LENGTH_TOO_HIGH);
        let err = sdo.write(5, 0x1000, 0, 1u32).await.unwrap_err();
        assert_eq!(err.abort_code(), AbortCode::READ_ONLY);
        assert!(err.to_string().contains("1000:00 on node 5"), "{err}");
        let blob: Vec<u8> = (0..5000u32).map(|i| i as u8).collect();
        let seen = std::sync::atomic::AtomicU64::new(0);
        let progress =
            |done: u64, _: Option<u64>| seen.store(done, std::sync::atomic::Ordering::Relaxed);
        let options = TransferOptions {
            how: Transfer::Block,
            progress: Some(&progress),
            ..TransferOptions::default()
        };
        sdo.write_with(5, 0x2000, 0, blob.clone(), options)
            .await
            .unwrap();
        assert_eq!(seen.load(std::sync::atomic::Ordering::Relaxed), 5000);
        assert_eq!(sdo.read_with(5, 0x2000, 0, options).await.unwrap(), blob);
        assert_eq!(od.lock().unwrap().read(0x2000, 0).unwrap(), blob);
        // No server at node 6: a timeout with the CiA code.
        let err = sdo.read_raw(6, 0x1000, 0).await.unwrap_err();
        assert_eq!(err.abort_code(), AbortCode::TIMEOUT);
        server.abort();
    }

    /// A transfer its caller gives up on mid-way (here: after its first segment) is aborted
    /// on the bus before the channel carries anything else, and the next transfer on the
    /// channel is served — without the abort the node's server, still in the first upload,
    /// refused the next request as out of place (05040001h).
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_transfer_given_up_on_is_aborted_before_the_next_goes_out() {
        let url = "mem://sdo-clients-given-up";
        let od = node_dictionary(7);
        od.lock().unwrap().write(0x2000, 0, &[0x5A; 700]).unwrap();
        let server = serve_sdo(
            Bus::open(url).await.unwrap(),
            od.clone(),
            5,
            ServerConfig::default(),
        );
        let mut monitor = Bus::open(url).await.unwrap();
        monitor
            .receiver
            .set_filters(&[Filter::exact(CanId::Standard(0x605))]);
        let sdo = SdoClients::new(Bus::open(url).await.unwrap(), ClientConfig::default());
        give_up_after_the_first_segment(&sdo).await;
        assert_eq!(sdo.read::<u32>(5, 0x1000, 0).await.unwrap(), 0x0001_01A1);
        let mut requests = Vec::new();
        while let Ok(Some(f)) =
            tokio::time::timeout(Duration::from_millis(100), monitor.receiver.recv_frame()).await
        {
            requests.push(f.data()[0]);
        }
        let abort = requests
            .iter()
            .position(|&cs| cs == 0x80)
            .expect("an abort");
        assert_eq!(
            requests[..abort].iter().filter(|&&cs| cs == 0x40).count(),
            1,
            "the abort comes before the next initiate: {requests:02X?}"
        );
        assert_eq!(
            requests[abort + 1..],
            [0x40],
            "then the next transfer alone: {requests:02X?}"
        );
        server.abort();
    }

    /// The answer to what a transfer given up on last asked can come after the next transfer
    /// on the channel has begun (the node answers in its own time): it is not taken for the
    /// next transfer's answer. A scripted node answers upload segments 50 ms late; without the
    /// channel held until it falls quiet, the read of 1000h got the late segment and failed
    /// with 05040001h.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_late_answer_to_a_transfer_given_up_on_is_not_the_next_ones() {
        let url = "mem://sdo-clients-late-answer";
        let script = scripted_node(url, |data| match (data[0], data[1], data[2]) {
            // 2000h: segmented, 700 bytes.
            (0x40, 0x00, 0x20) => now([0x41, 0x00, 0x20, 0x00, 0xBC, 0x02, 0, 0]),
            (0x60 | 0x70, ..) => (
                Duration::from_millis(50),
                Some([data[0] & 0x10, 1, 2, 3, 4, 5, 6, 7]),
            ),
            (0x40, 0x00, 0x10) => now(DEVICE_TYPE),
            _ => now(refused(data)),
        })
        .await;
        let sdo = SdoClients::new(Bus::open(url).await.unwrap(), ClientConfig::default());
        give_up_after_the_first_segment(&sdo).await;
        let read = sdo.read::<u32>(5, 0x1000, 0).await;
        script.abort();
        let heard = script.await.unwrap_or_default();
        assert_eq!(read.unwrap(), 0x0001_01A1, "the node heard {heard:02X?}");
    }

    /// A channel check given up on (its future dropped, as the gateway's start does when its
    /// time is up) is a transfer given up on like any other: the late answer to its read of
    /// 1000h is not taken for the next transfer's. Without the check's reads held until quiet,
    /// the read of 1001h got 1000h's answer and failed.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_channel_check_given_up_on_leaves_its_late_answer_behind() {
        let url = "mem://sdo-clients-check-given-up";
        let script = scripted_node(url, |data| match (data[0], data[1], data[2]) {
            (0x40, 0x00, 0x10) => (Duration::from_millis(100), Some(DEVICE_TYPE)),
            (0x40, 0x01, 0x10) => now([0x4F, 0x01, 0x10, 0x00, 0x00, 0, 0, 0]),
            _ => now(refused(data)),
        })
        .await;
        let sdo = SdoClients::new(Bus::open(url).await.unwrap(), ClientConfig::default());
        let check = tokio::time::timeout(Duration::from_millis(20), sdo.check_channels(5)).await;
        assert!(check.is_err(), "the check was given up on");
        let read = sdo.read::<u8>(5, 0x1001, 0).await;
        script.abort();
        assert_eq!(read.unwrap(), 0);
    }

    /// What a scripted node answers a request: after how long, and what (nothing for `None`).
    type Scripted = (Duration, Option<[u8; 8]>);

    /// An answer sent at once.
    fn now(answer: [u8; 8]) -> Scripted {
        (Duration::ZERO, Some(answer))
    }

    /// The answer to a read of 1000h: device type 000101A1h.
    const DEVICE_TYPE: [u8; 8] = [0x43, 0x00, 0x10, 0x00, 0xA1, 0x01, 0x01, 0x00];

    /// The abort 05040001h (command specifier not valid) of the request `data`: what the
    /// script does not expect.
    fn refused(data: &[u8]) -> [u8; 8] {
        [0x80, data[1], data[2], data[3], 0x01, 0x00, 0x04, 0x05]
    }

    /// Node 5 on `url`'s default SDO channel, answering each request as `answer` says, one
    /// after the other (a server serves its channel in order), and no abort (CiA 301
    /// §7.2.4.3.17: an abort is not confirmed); what it heard (command bytes) when stopped.
    async fn scripted_node(
        url: &str,
        answer: impl Fn(&[u8]) -> Scripted + Send + 'static,
    ) -> tokio::task::JoinHandle<Vec<u8>> {
        let mut node = Bus::open(url).await.unwrap();
        node.receiver
            .set_filters(&[Filter::exact(CanId::Standard(0x605))]);
        tokio::spawn(async move {
            let mut heard = Vec::new();
            while let Some(request) = node.receiver.recv_frame().await {
                heard.push(request.data()[0]);
                if request.data()[0] == 0x80 {
                    continue;
                }
                let (after, answer) = answer(request.data());
                tokio::time::sleep(after).await;
                let Some(answer) = answer else { continue };
                let answer = Frame::new(CanId::Standard(0x585), &answer).unwrap();
                if node.sender.send(answer).await.is_err() {
                    break;
                }
            }
            heard
        })
    }

    /// Read 2000h of node 5 segmented, and give the read up once its first segment is in.
    async fn give_up_after_the_first_segment(sdo: &SdoClients) {
        struct Notifying(Arc<tokio::sync::Notify>);
        impl std::io::Write for Notifying {
            fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
                self.0.notify_one();
                Ok(buf.len())
            }
            fn flush(&mut self) -> std::io::Result<()> {
                Ok(())
            }
        }
        let arrived = Arc::new(tokio::sync::Notify::new());
        let mut sink = Notifying(arrived.clone());
        let options = TransferOptions {
            how: Transfer::Segmented,
            ..TransferOptions::default()
        };
        tokio::select! {
            read = sdo.read_to(5, 0x2000, 0, &mut sink, options) => panic!("700 bytes in one segment? {read:?}"),
            () = arrived.notified() => {}
        }
    }

    /// The abort as it goes out: the transfer's object and 08000000h.
    #[tokio::test]
    async fn the_abort_of_a_transfer_given_up_on_names_its_object() {
        let url = "mem://sdo-clients-abort-frame";
        let mut monitor = Bus::open(url).await.unwrap();
        monitor
            .receiver
            .set_filters(&[Filter::exact(CanId::Standard(0x609))]);
        let sdo = SdoClients::new(Bus::open(url).await.unwrap(), ClientConfig::default());
        // No server: the read waits for its answer and is given up on.
        let read = sdo.read_raw(9, 0x2001, 3);
        assert!(tokio::time::timeout(Duration::from_millis(20), read)
            .await
            .is_err());
        let initiate = monitor.receiver.recv_frame().await.unwrap();
        assert_eq!(initiate.data(), [0x40, 0x01, 0x20, 0x03, 0, 0, 0, 0]);
        let abort = tokio::time::timeout(Duration::from_secs(5), monitor.receiver.recv_frame())
            .await
            .expect("an abort")
            .unwrap();
        assert_eq!(abort.data(), [0x80, 0x01, 0x20, 0x03, 0, 0, 0, 0x08]);
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn concurrent_nodes_and_queued_transfers_to_one_node() {
        let url = "mem://sdo-clients-concurrent";
        let mut servers = Vec::new();
        for node in 1..=4u8 {
            servers.push(serve_sdo(
                Bus::open(url).await.unwrap(),
                node_dictionary(node.into()),
                node,
                ServerConfig::default(),
            ));
        }
        let sdo = SdoClients::new(Bus::open(url).await.unwrap(), ClientConfig::default());
        let mut tasks = Vec::new();
        for i in 0..40u32 {
            let sdo = sdo.clone();
            let node = (i % 4 + 1) as u8;
            tasks.push(tokio::spawn(async move {
                let data = vec![i as u8; 100 + i as usize];
                sdo.write_raw(node, 0x2000, 0, &data).await.unwrap();
                let serial = sdo.read::<u32>(node, 0x1018, 0).await.unwrap();
                assert_eq!(serial, u32::from(node));
            }));
        }
        for t in tasks {
            t.await.unwrap();
        }
        for s in servers {
            s.abort();
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn configured_channels_carry_the_transfers() {
        let url = "mem://sdo-clients-channels";
        let od = node_dictionary(7);
        let u32v = |v: u32| {
            Variable::new("COB-ID", DataType::Unsigned32, Access::Ro)
                .with_value(Value::Uint(v.into()))
        };
        od.lock().unwrap().insert(Object::composite(
            0x1201,
            "SDO server 2",
            crate::od::ObjectCode::Record,
            [(1, u32v(0x640)), (2, u32v(0x5C0))],
        ));
        let server = serve_sdo(
            Bus::open(url).await.unwrap(),
            od,
            7,
            ServerConfig::default(),
        );
        let mut client_od = ObjectDictionary::new();
        client_od.insert(Object::composite(
            0x1280,
            "SDO client 1",
            crate::od::ObjectCode::Record,
            [(1, u32v(0x640)), (2, u32v(0x5C0)), (3, u32v(7))],
        ));
        let channels = client_channels(&client_od);
        assert_eq!(
            channels,
            vec![(7, CanId::Standard(0x640), CanId::Standard(0x5C0))]
        );
        let mut monitor = Bus::open(url).await.unwrap();
        let sdo = SdoClients::with_channels(
            Bus::open(url).await.unwrap(),
            ClientConfig::default(),
            &channels,
        );
        assert_eq!(sdo.read::<u32>(7, 0x1018, 0).await.unwrap(), 7);
        let ids: Vec<CanId> = [
            monitor.receiver.recv_frame().await.unwrap(),
            monitor.receiver.recv_frame().await.unwrap(),
        ]
        .iter()
        .map(|f| f.id())
        .collect();
        assert_eq!(ids, vec![CanId::Standard(0x640), CanId::Standard(0x5C0)]);
        server.abort();
    }

    /// Node 7's default channel and two further ones (1201h, 1202h) as client channels.
    fn three_channels() -> Vec<(u8, CanId, CanId)> {
        [(0x607, 0x587), (0x6A1, 0x6C1), (0x6A2, 0x6C2)]
            .into_iter()
            .map(|(req, resp)| (7, CanId::Standard(req), CanId::Standard(resp)))
            .collect()
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_node_with_several_channels_serves_as_many_transfers_at_once() {
        // No server answers: each transfer holds its channel until it times out, so what the
        // bus shows first is what was started at once.
        let url = "mem://sdo-clients-channels-at-once";
        let mut monitor = Bus::open(url).await.unwrap();
        let config = ClientConfig {
            timeout: Duration::from_millis(300),
            ..ClientConfig::default()
        };
        let sdo =
            SdoClients::with_channels(Bus::open(url).await.unwrap(), config, &three_channels());
        let reads: Vec<_> = (0..4)
            .map(|_| {
                let sdo = sdo.clone();
                tokio::spawn(async move { sdo.read_raw(7, 0x1018, 0).await })
            })
            .collect();
        let mut first = Vec::new();
        for _ in 0..3 {
            first.push(monitor.receiver.recv_frame().await.unwrap());
        }
        let mut ids: Vec<CanId> = first.iter().map(|f| f.id()).collect();
        ids.sort();
        let mut requests: Vec<CanId> = three_channels().iter().map(|c| c.1).collect();
        requests.sort();
        assert_eq!(
            ids, requests,
            "three initiate requests, one on each channel"
        );
        // The fourth waits for a channel: nothing more on the bus before the timeouts.
        assert!(
            tokio::time::timeout(Duration::from_millis(150), monitor.receiver.recv_frame())
                .await
                .is_err(),
            "a fourth transfer started while all channels were busy"
        );
        for read in reads {
            let err = read.await.unwrap().unwrap_err();
            assert_eq!(err.abort_code(), AbortCode::TIMEOUT);
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn transfers_on_several_channels_to_one_node_keep_their_answers_apart() {
        let url = "mem://sdo-clients-channels-apart";
        let od = node_dictionary(7);
        {
            let mut od = od.lock().unwrap();
            od.insert(server_channel(0x1201, 0x6A1, 0x6C1));
            od.insert(server_channel(0x1202, 0x6A2, 0x6C2));
            for i in 0..12u16 {
                od.insert(Object::var(
                    0x2100 + i,
                    Variable::new("Blob", DataType::Domain, Access::Rw),
                ));
            }
        }
        let server = serve_sdo(
            Bus::open(url).await.unwrap(),
            od,
            7,
            ServerConfig::default(),
        );
        let mut monitor = Bus::open(url).await.unwrap();
        let sdo = SdoClients::with_channels(
            Bus::open(url).await.unwrap(),
            ClientConfig::default(),
            &three_channels(),
        );
        let tasks: Vec<_> = (0..12u16)
            .map(|i| {
                let sdo = sdo.clone();
                tokio::spawn(async move {
                    // Segmented both ways: many frames per transfer, interleaved on the bus.
                    let data = vec![i as u8; 60 + usize::from(i)];
                    sdo.write_raw(7, 0x2100 + i, 0, &data).await.unwrap();
                    assert_eq!(sdo.read_raw(7, 0x2100 + i, 0).await.unwrap(), data);
                })
            })
            .collect();
        for t in tasks {
            t.await.unwrap();
        }
        let mut used = std::collections::BTreeSet::new();
        while let Ok(Some(f)) =
            tokio::time::timeout(Duration::from_millis(50), monitor.receiver.recv_frame()).await
        {
            used.insert(f.id());
        }
        for (_, req, resp) in three_channels() {
            assert!(
                used.contains(&req) && used.contains(&resp),
                "{req:?} unused"
            );
        }
        server.abort();
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_channel_the_node_does_not_serve_is_found() {
        let url = "mem://sdo-clients-channels-checked";
        let od = node_dictionary(7);
        let server = serve_with(url, &od, server_channel(0x1201, 0x6A1, 0x6C1)).await;
        let config = ClientConfig {
            timeout: Duration::from_millis(200),
            ..ClientConfig::default()
        };
        // 1202h (6A2h/6C2h) is configured here but not on the node.
        let sdo =
            SdoClients::with_channels(Bus::open(url).await.unwrap(), config, &three_channels());
        let answers = sdo.check_channels(7).await.unwrap();
        let answered: Vec<(u16, bool)> = answers
            .iter()
            .map(|((request, _), answer)| (request.as_raw() as u16, answer.is_ok()))
            .collect();
        assert_eq!(answered, vec![(0x607, true), (0x6A1, true), (0x6A2, false)]);
        let silent = answers.into_iter().find_map(|(_, a)| a.err()).unwrap();
        assert_eq!(silent.abort_code(), AbortCode::TIMEOUT);
        server.abort();
    }

    /// Server channel object `index` (1201h ff.) with identifiers `request`/`response`.
    fn server_channel(index: u16, request: u32, response: u32) -> Object {
        Object::composite(
            index,
            "SDO server",
            crate::od::ObjectCode::Record,
            [request, response].into_iter().zip(1u8..).map(|(v, sub)| {
                let var = Variable::new("COB-ID", DataType::Unsigned32, Access::Ro)
                    .with_value(Value::Uint(v.into()));
                (sub, var)
            }),
        )
    }

    /// Node 7 serving `od` on `url`, `channel` (a further server channel) added to it first.
    async fn serve_with(url: &str, od: &SharedDictionary, channel: Object) -> JoinHandle<()> {
        od.lock().unwrap().insert(channel);
        let bus = Bus::open(url).await.unwrap();
        serve_sdo(bus, od.clone(), 7, ServerConfig::default())
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn a_channel_that_falls_silent_is_set_aside_and_taken_back_when_it_answers() {
        let url = "mem://sdo-clients-channel-set-aside";
        let config = ClientConfig {
            timeout: Duration::from_millis(100),
            ..ClientConfig::default()
        };
        let sdo =
            SdoClients::with_channels(Bus::open(url).await.unwrap(), config, &three_channels());
        sdo.set_probe_interval(Duration::from_millis(200));
        let read = || async { sdo.read::<u32>(7, 0x1000, 0).await.is_ok() };
        // The node is off: every channel is silent, and none is set aside for it.
        for _ in 0..9 {
            assert!(!read().await);
        }
        assert_eq!(sdo.check_channels(7).await.unwrap().len(), 3);
        // The node serves two of the three (1202h, 6A2h/6C2h, is not on it): one read in
        // three fails — taken in turn — until 6A2h is set aside: its third timeout in a row,
        // the first of them while the node was off.
        let od = node_dictionary(7);
        let server = serve_with(url, &od, server_channel(0x1201, 0x6A1, 0x6C1)).await;
        let mut answered = Vec::new();
        for _ in 0..15 {
            answered.push(read().await);
        }
        assert_eq!(
            answered.iter().filter(|ok| !**ok).count(),
            2,
            "{answered:?}"
        );
        assert!(answered[6..].iter().all(|ok| *ok), "{answered:?}");
        let in_service: Vec<u32> = sdo
            .check_channels(7)
            .await
            .unwrap()
            .into_iter()
            .map(|((request, _), answer)| {
                assert!(answer.is_ok());
                request.as_raw()
            })
            .collect();
        assert_eq!(in_service, [0x607, 0x6A1]);
        // The node opens 1202h: the next probe finds it, and it carries transfers again.
        server.abort();
        let server = serve_with(url, &od, server_channel(0x1202, 0x6A2, 0x6C2)).await;
        let back = tokio::time::timeout(Duration::from_secs(5), async {
            loop {
                tokio::time::sleep(Duration::from_millis(100)).await;
                let answers = sdo.check_channels(7).await.unwrap();
                if answers.len() == 3 && answers.iter().all(|(_, a)| a.is_ok()) {
                    return;
                }
            }
        });
        assert!(back.await.is_ok(), "6A2h back in service");
        server.abort();
    }

    /// One MiB of a pattern, generated on demand (never held in memory).
    const BIG: u64 = 1 << 20;
    fn pattern_byte(i: u64) -> u8 {
        (i.wrapping_mul(2_654_435_761) >> 7) as u8
    }

    struct Generated;
    impl DownloadSource for Generated {
        fn len(&self) -> u64 {
            BIG
        }
        fn read_at(&mut self, offset: u64, buf: &mut [u8]) -> std::io::Result<()> {
            for (i, b) in buf.iter_mut().enumerate() {
                *b = pattern_byte(offset + i as u64);
            }
            Ok(())
        }
    }

    /// A server-side DOMAIN that checks what is written and produces the pattern on reads.
    #[derive(Default)]
    struct Checked {
        written: std::sync::atomic::AtomicU64,
        errors: std::sync::atomic::AtomicU64,
    }
    impl crate::od::DomainStream for Checked {
        fn size(&self) -> Option<u64> {
            Some(BIG)
        }
        fn read_at(&self, offset: u64, buf: &mut [u8]) -> Result<usize, AbortCode> {
            let n = buf.len().min((BIG - offset.min(BIG)) as usize);
            for (i, b) in buf[..n].iter_mut().enumerate() {
                *b = pattern_byte(offset + i as u64);
            }
            Ok(n)
        }
        fn begin_write(&self, _: Option<u64>) -> Result<(), AbortCode> {
            self.written.store(0, std::sync::atomic::Ordering::Relaxed);
            Ok(())
        }
        fn write_chunk(&self, offset: u64, data: &[u8]) -> Result<(), AbortCode> {
            let bad = data
                .iter()
                .enumerate()
                .filter(|(i, b)| **b != pattern_byte(offset + *i as u64))
                .count();
            self.errors
                .fetch_add(bad as u64, std::sync::atomic::Ordering::Relaxed);
            self.written
                .fetch_add(data.len() as u64, std::sync::atomic::Ordering::Relaxed);
            Ok(())
        }
        fn end_write(&self, _: u64) -> Result<(), AbortCode> {
            Ok(())
        }
    }

    /// Verifies uploaded bytes as they arrive instead of keeping them.
    struct Verifier {
        pos: u64,
        errors: u64,
        largest_chunk: usize,
    }
    impl std::io::Write for Verifier {
        fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
            for b in buf {
                self.errors += u64::from(*b != pattern_byte(self.pos));
                self.pos += 1;
            }
            self.largest_chunk = self.largest_chunk.max(buf.len());
            Ok(buf.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn large_domains_stream_both_ways() {
        let url = "mem://sdo-clients-stream";
        let stream = Arc::new(Checked::default());
        let mut od = ObjectDictionary::new();
        od.insert(Object::var(
            0x2100,
            Variable::new("Image", DataType::Domain, Access::Rw).with_stream(stream.clone()),
        ));
        let server = serve_sdo(
            Bus::open(url).await.unwrap(),
            Arc::new(Mutex::new(od)),
            3,
            ServerConfig::default(),
        );
        let options = BusOptions {
            rx_queue: 1 << 16,
            ..BusOptions::default()
        };
        let sdo = SdoClients::new(
            Bus::open_with(url, options).await.unwrap(),
            ClientConfig::default(),
        );
        // Segmented streaming shares the sink path; 1 MiB of it would cost seconds of test time.
        for how in [Transfer::Block] {
            let options = TransferOptions {
                how,
                ..TransferOptions::default()
            };
            sdo.write_from(3, 0x2100, 0, Box::new(Generated), options)
                .await
                .unwrap();
            assert_eq!(
                stream.written.load(std::sync::atomic::Ordering::Relaxed),
                BIG,
                "{how:?}"
            );
            assert_eq!(
                stream.errors.load(std::sync::atomic::Ordering::Relaxed),
                0,
                "{how:?}"
            );
            let mut verifier = Verifier {
                pos: 0,
                errors: 0,
                largest_chunk: 0,
            };
            assert_eq!(
                sdo.read_to(3, 0x2100, 0, &mut verifier, options)
                    .await
                    .unwrap(),
                BIG
            );
            assert_eq!((verifier.pos, verifier.errors), (BIG, 0), "{how:?}");
            assert!(
                verifier.largest_chunk < 64 * 1024,
                "{how:?}: data was buffered ({} bytes at once)",
                verifier.largest_chunk
            );
        }
        server.abort();
    }
}
