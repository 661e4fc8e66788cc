//! The [`Bus`]: one endpoint on a CAN bus, whatever carries it.
//!
//! An endpoint is a [`BusReceiver`] (one per endpoint, with its own acceptance filters) and any
//! number of cheap [`BusSender`] clones. Backends are chosen by URL (docs/ARCHITECTURE.md §Conventions):
//! `mem://NAME`, `socketcand://HOST:PORT/CHANNEL`, `socketcan://IFACE`.
//!
//! [`Bus::open`] opens an endpoint with a link of its own (one TCP connection to socketcand);
//! [`Interface::open`] opens the link once and [`Interface::endpoint`] any number of endpoints on
//! it, as several SocketCAN sockets share one interface: each sees what the others send and
//! everything on the bus, and a frame its filters refuse never wakes it.

use std::fmt;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock};

use tokio::sync::mpsc;

use crate::frame::{Filter, Frame};
use crate::{mem, socketcand};

/// Default TCP port of socketcand and of `canlift hub`.
pub const SOCKETCAND_DEFAULT_PORT: u16 = 29536;

/// Frames an endpoint buffers before it counts overruns (like a SocketCAN receive queue).
pub const DEFAULT_RX_QUEUE: usize = 8192;

/// Why a bus operation failed.
#[derive(Debug, thiserror::Error)]
pub enum BusError {
    /// The URL is not one of the supported forms.
    #[error("invalid bus URL {url:?}: {reason}")]
    InvalidUrl {
        /// The URL as given.
        url: String,
        /// What is wrong with it.
        reason: String,
    },
    /// The link to a remote bus is down; the frame was not sent.
    #[error("bus link {link} is down; frame not sent")]
    Offline {
        /// Which link (`socketcand://…`).
        link: String,
    },
    /// The backend has shut down.
    #[error("bus endpoint is closed")]
    Closed,
    /// The frame cannot be carried by this backend (e.g. a remote frame over socketcand).
    #[error("{0}")]
    Unsupported(String),
    /// An I/O error from the operating system.
    #[error("{context}: {source}")]
    Io {
        /// What was being done.
        context: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The remote end broke the protocol during set-up.
    #[error("{0}")]
    Protocol(String),
}

impl BusError {
    pub(crate) fn io(context: impl Into<String>, source: std::io::Error) -> Self {
        BusError::Io {
            context: context.into(),
            source,
        }
    }
}

/// Something that happened on an endpoint: a frame, or news about the link.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BusEvent {
    /// A frame that passed the endpoint's filters.
    Frame(Frame),
    /// The link to the bus came back (after [`BusEvent::LinkDown`]).
    LinkUp,
    /// The link to the bus is lost; frames sent meanwhile fail with [`BusError::Offline`].
    LinkDown {
        /// Why, for logs and operators.
        reason: String,
    },
    /// The receive queue was full and this many frames were dropped since the last report.
    Overrun {
        /// Frames lost.
        dropped: u64,
    },
}

/// A parsed bus URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum BusUrl {
    /// `mem://NAME`: an in-process bus shared by everything in this process that opens NAME.
    Mem(String),
    /// `socketcand://HOST:PORT/CHANNEL`: a socketcand server (or `canlift hub`).
    Socketcand {
        /// Host name or address.
        host: String,
        /// TCP port (default 29536).
        port: u16,
        /// The channel (bus) name on that server.
        channel: String,
    },
    /// `socketcan://IFACE`: a Linux SocketCAN interface.
    Socketcan(String),
}

impl std::str::FromStr for BusUrl {
    type Err = BusError;

    fn from_str(url: &str) -> Result<Self, BusError> {
        let bad = |reason: &str| BusError::InvalidUrl {
            url: url.to_owned(),
            reason: reason.to_owned(),
        };
        let (scheme, rest) = url
            .split_once("://")
            .ok_or_else(|| bad("expected SCHEME://…"))?;
        let valid_name =
            |s: &str| !s.is_empty() && s.len() <= 64 && s.bytes().all(|b| b.is_ascii_graphic());
        match scheme {
            "mem" if valid_name(rest) => Ok(BusUrl::Mem(rest.to_owned())),
            "mem" => Err(bad("mem:// needs a bus name")),
            "socketcan" if valid_name(rest) && !rest.contains('/') && rest.len() < 16 => {
                Ok(BusUrl::Socketcan(rest.to_owned()))
            }
            "socketcan" => Err(bad(
                "socketcan:// needs an interface name of 1-15 characters",
            )),
            "socketcand" => {
                let (authority, channel) = rest
                    .split_once('/')
                    .ok_or_else(|| bad("socketcand:// needs HOST[:PORT]/CHANNEL"))?;
                if !valid_name(channel) || channel.contains('/') {
                    return Err(bad("socketcand:// needs a channel name after the host"));
                }
                let (host, port) = split_host_port(authority)
                    .ok_or_else(|| bad("socketcand:// has an invalid host or port"))?;
                Ok(BusUrl::Socketcand {
                    host,
                    port,
                    channel: channel.to_owned(),
                })
            }
            _ => Err(bad("supported schemes: mem, socketcand, socketcan")),
        }
    }
}

fn split_host_port(authority: &str) -> Option<(String, u16)> {
    let (host, port) = if let Some(v6) = authority.strip_prefix('[') {
        let (host, after) = v6.split_once(']')?;
        (host, after.strip_prefix(':'))
    } else {
        match authority.rsplit_once(':') {
            Some((host, port)) => (host, Some(port)),
            None => (authority, None),
        }
    };
    if host.is_empty() {
        return None;
    }
    let port = match port {
        Some(p) => p.parse().ok().filter(|&p| p != 0)?,
        None => SOCKETCAND_DEFAULT_PORT,
    };
    Some((host.to_owned(), port))
}

impl fmt::Display for BusUrl {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            BusUrl::Mem(name) => write!(f, "mem://{name}"),
            BusUrl::Socketcand {
                host,
                port,
                channel,
            } if host.contains(':') => write!(f, "socketcand://[{host}]:{port}/{channel}"),
            BusUrl::Socketcand {
                host,
                port,
                channel,
            } => write!(f, "socketcand://{host}:{port}/{channel}"),
            BusUrl::Socketcan(iface) => write!(f, "socketcan://{iface}"),
        }
    }
}

/// How an endpoint is opened.
#[derive(Debug, Clone)]
pub struct BusOptions {
    /// Deliver this endpoint's own frames back to it (off by default, as on SocketCAN).
    pub receive_own: bool,
    /// Frames buffered for the receiver before overruns are counted.
    pub rx_queue: usize,
}

impl Default for BusOptions {
    fn default() -> Self {
        BusOptions {
            receive_own: false,
            rx_queue: DEFAULT_RX_QUEUE,
        }
    }
}

/// The sending half of an endpoint; clone it freely (an `Arc` inside).
#[derive(Clone)]
pub struct BusSender {
    inner: SenderInner,
}

#[derive(Clone)]
pub(crate) enum SenderInner {
    Mem(mem::MemSender),
    Socketcand(socketcand::client::ClientSender),
    #[cfg(target_os = "linux")]
    Socketcan(crate::socketcan::SocketcanSender),
}

impl BusSender {
    pub(crate) fn new(inner: SenderInner) -> Self {
        BusSender { inner }
    }

    /// Put `frame` on the bus. Waits while the backend's transmit queue is full.
    pub async fn send(&self, frame: Frame) -> Result<(), BusError> {
        match &self.inner {
            SenderInner::Mem(s) => s.send(frame),
            SenderInner::Socketcand(s) => s.send(frame).await,
            #[cfg(target_os = "linux")]
            SenderInner::Socketcan(s) => s.send(frame).await,
        }
    }
}

impl BusSender {
    /// Wait until every frame sent so far has left this process (written to the socket or
    /// handed to the kernel). Call it before exiting, or a frame still queued for a socketcand
    /// link is lost.
    pub async fn flush(&self) -> Result<(), BusError> {
        match &self.inner {
            SenderInner::Socketcand(s) => s.flush().await,
            // Sends on these complete synchronously (in-process delivery, kernel write).
            SenderInner::Mem(_) => Ok(()),
            #[cfg(target_os = "linux")]
            SenderInner::Socketcan(_) => Ok(()),
        }
    }
}

impl fmt::Debug for BusSender {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("BusSender")
    }
}

/// An endpoint's acceptance filters, shared by its receiver (which sets them) and its feed
/// (which applies them before queueing, as SocketCAN filters in the kernel: a refused frame
/// takes no room in the queue and wakes nobody).
type SharedFilters = Arc<RwLock<Vec<Filter>>>;

fn accepted(filters: &[Filter], frame: &Frame) -> bool {
    filters.is_empty() || filters.iter().any(|f| f.matches(frame))
}

/// What a receiver turned into a handler ([`BusReceiver::handle_with`]) does with each event.
type Handler = Box<dyn Fn(BusEvent) + Send + Sync>;

/// An endpoint's handler, once it has one: shared by the receiver (which sets it) and its feed
/// (which calls it instead of queueing). One lock for both, so that no event is queued after
/// the queue was handed over.
type SharedHandler = Arc<Mutex<Option<Handler>>>;

/// The backend side of an endpoint's receive queue.
#[derive(Clone)]
pub(crate) struct RxFeed {
    tx: mpsc::Sender<BusEvent>,
    overruns: Arc<AtomicU64>,
    filters: SharedFilters,
    handler: SharedHandler,
}

impl RxFeed {
    /// Queue an event without waiting unless the endpoint's filters refuse it; a full queue
    /// counts an overrun. Returns `false` once the receiver is gone, so the backend can stop
    /// feeding it.
    pub(crate) fn push(&self, event: BusEvent) -> bool {
        if let BusEvent::Frame(frame) = &event {
            let filters = self.filters.read().unwrap_or_else(PoisonError::into_inner);
            if !accepted(&filters, frame) {
                return !self.tx.is_closed();
            }
        }
        match self.offer(event) {
            Ok(open) => open,
            Err(_) => {
                self.overruns.fetch_add(1, Ordering::Relaxed);
                true
            }
        }
    }

    /// Queue a link event, waiting for room: those must not be lost to an overrun.
    pub(crate) async fn push_link(&self, event: BusEvent) -> bool {
        match self.offer(event) {
            Ok(open) => open,
            // Only a queue left unread this long can be full when it is handed to a handler;
            // this event then stays in it.
            Err(event) => self.tx.send(event).await.is_ok(),
        }
    }

    /// Hand `event` to the endpoint's handler, or queue it without waiting — under the
    /// handler's lock, so that nothing is queued once the queue has been handed over. Whether
    /// the endpoint is still open; the event back if the queue is full.
    fn offer(&self, event: BusEvent) -> Result<bool, BusEvent> {
        let handler = self.handler.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(handle) = handler.as_ref() {
            // Once the endpoint is dropped nothing more reaches its handler, which goes with
            // the endpoint when the bus prunes it.
            if self.tx.is_closed() {
                return Ok(false);
            }
            handle(event);
            return Ok(true);
        }
        match self.tx.try_send(event) {
            Ok(()) => Ok(true),
            Err(mpsc::error::TrySendError::Full(event)) => Err(event),
            Err(mpsc::error::TrySendError::Closed(_)) => Ok(false),
        }
    }

    pub(crate) fn is_closed(&self) -> bool {
        self.tx.is_closed()
    }

    /// Resolves once the receiver is gone.
    pub(crate) async fn closed(&self) {
        self.tx.closed().await
    }
}

/// The endpoints a backend delivers to: those of one `mem://` bus, or of one link.
#[derive(Default)]
pub(crate) struct Endpoints {
    list: RwLock<Vec<Endpoint>>,
    next_id: AtomicU64,
}

struct Endpoint {
    id: u64,
    feed: RxFeed,
    receive_own: bool,
}

impl Endpoints {
    /// Add an endpoint; its id, for [`Endpoints::deliver`].
    pub(crate) fn add(&self, feed: RxFeed, receive_own: bool) -> u64 {
        let id = self.next_id.fetch_add(1, Ordering::Relaxed);
        self.list
            .write()
            .unwrap_or_else(PoisonError::into_inner)
            .push(Endpoint {
                id,
                feed,
                receive_own,
            });
        id
    }

    /// Hand `frame` to every endpoint but the one it came `from` (unless that one asked for its
    /// own frames); endpoints whose receiver is gone are dropped.
    pub(crate) fn deliver(&self, from: Option<u64>, frame: Frame) {
        let mut any_closed = false;
        {
            // Written, not read: one delivery at a time, so that every endpoint sees the frames
            // in the same order, as every node on a CAN bus does. Under a shared lock a node
            // that answers at once (an SDO server on another thread) could reach a third
            // endpoint before the request it answers did.
            let list = self.list.write().unwrap_or_else(PoisonError::into_inner);
            for ep in list.iter() {
                if Some(ep.id) != from || ep.receive_own {
                    any_closed |= !ep.feed.push(BusEvent::Frame(frame));
                }
            }
        }
        if any_closed {
            self.prune();
        }
    }

    /// Drop the endpoints whose receiver is gone; whether none is left.
    pub(crate) fn prune(&self) -> bool {
        let mut list = self.list.write().unwrap_or_else(PoisonError::into_inner);
        list.retain(|ep| !ep.feed.is_closed());
        list.is_empty()
    }

    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.list
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .len()
    }

    fn feeds(&self) -> Vec<RxFeed> {
        let list = self.list.read().unwrap_or_else(PoisonError::into_inner);
        list.iter().map(|ep| ep.feed.clone()).collect()
    }

    /// Tell every endpoint about the link (waiting for room: link events are never lost).
    pub(crate) async fn announce(&self, event: BusEvent) {
        for feed in self.feeds() {
            feed.push_link(event.clone()).await;
        }
    }

    /// Resolves once every endpoint's receiver is gone.
    pub(crate) async fn closed(&self) {
        loop {
            for feed in self.feeds() {
                feed.closed().await;
            }
            if self.prune() {
                return;
            }
        }
    }
}

/// The receiving half of an endpoint.
pub struct BusReceiver {
    rx: mpsc::Receiver<BusEvent>,
    overruns: Arc<AtomicU64>,
    filters: SharedFilters,
    handler: SharedHandler,
}

impl fmt::Debug for BusReceiver {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("BusReceiver")
            .field("queued", &self.rx.len())
            .finish_non_exhaustive()
    }
}

/// An endpoint whose events go to a handler ([`BusReceiver::handle_with`]); dropping it closes
/// the endpoint.
pub struct Handled {
    _receiver: BusReceiver,
}

impl fmt::Debug for Handled {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("Handled")
    }
}

impl BusReceiver {
    pub(crate) fn channel(capacity: usize) -> (RxFeed, BusReceiver) {
        let (tx, rx) = mpsc::channel(capacity.max(1));
        let overruns = Arc::new(AtomicU64::new(0));
        let filters = SharedFilters::default();
        let handler = SharedHandler::default();
        (
            RxFeed {
                tx,
                overruns: overruns.clone(),
                filters: filters.clone(),
                handler: handler.clone(),
            },
            BusReceiver {
                rx,
                overruns,
                filters,
                handler,
            },
        )
    }

    /// Hand every event this endpoint accepts to `handler`, called by the task that delivers
    /// it (the link's reader, or a sender on the same bus) instead of queueing it for a task
    /// of the endpoint's own: one hand-over and one wake-up less per frame, for an endpoint
    /// that only sorts frames into queues of its own (an SDO client routing answers to their
    /// transfers). Events queued so far go to `handler` first, in order. The endpoint lives
    /// while the returned [`Handled`] does.
    ///
    /// `handler` runs while the bus delivers to its endpoints, one frame at a time: it must not
    /// block, wait or send on this bus (a send delivers too, and would wait for itself), nor
    /// drop the last reference to what holds the [`Handled`] (its drop would wait for the
    /// delivery it is part of): share the state it needs rather than a `Weak` to its owner.
    /// After the `Handled` is dropped no event reaches `handler`; it is dropped itself when
    /// the bus next delivers and finds the endpoint gone.
    pub fn handle_with(mut self, handler: impl Fn(BusEvent) + Send + Sync + 'static) -> Handled {
        let shared = self.handler.clone();
        let mut slot = shared.lock().unwrap_or_else(PoisonError::into_inner);
        while let Some(event) = self.try_recv() {
            handler(event);
        }
        *slot = Some(Box::new(handler));
        drop(slot);
        Handled { _receiver: self }
    }

    /// Accept only frames matching at least one of `filters`; an empty list accepts all. Frames
    /// refused are not queued at all; frames queued before the change are filtered as they are
    /// received.
    pub fn set_filters(&mut self, filters: &[Filter]) {
        *self.filters.write().unwrap_or_else(PoisonError::into_inner) = filters.to_vec();
    }

    fn accepts(&self, frame: &Frame) -> bool {
        accepted(
            &self.filters.read().unwrap_or_else(PoisonError::into_inner),
            frame,
        )
    }

    fn take_overrun(&self) -> Option<BusEvent> {
        let dropped = self.overruns.swap(0, Ordering::Relaxed);
        (dropped > 0).then_some(BusEvent::Overrun { dropped })
    }

    /// The next event; `None` once the backend is gone for good.
    pub async fn recv(&mut self) -> Option<BusEvent> {
        loop {
            if let Some(overrun) = self.take_overrun() {
                return Some(overrun);
            }
            match self.rx.recv().await? {
                BusEvent::Frame(f) if !self.accepts(&f) => continue,
                event => return Some(event),
            }
        }
    }

    /// The next event if one is queued, without waiting.
    pub fn try_recv(&mut self) -> Option<BusEvent> {
        loop {
            if let Some(overrun) = self.take_overrun() {
                return Some(overrun);
            }
            match self.rx.try_recv().ok()? {
                BusEvent::Frame(f) if !self.accepts(&f) => continue,
                event => return Some(event),
            }
        }
    }

    /// The next frame, skipping link and overrun events; `None` once the backend is gone.
    pub async fn recv_frame(&mut self) -> Option<Frame> {
        loop {
            if let BusEvent::Frame(f) = self.recv().await? {
                return Some(f);
            }
        }
    }
}

/// One endpoint on a bus: a receiver and a sender.
#[derive(Debug)]
pub struct Bus {
    /// Sends on this endpoint; clone it to send from several tasks.
    pub sender: BusSender,
    /// Receives what others sent.
    pub receiver: BusReceiver,
    url: BusUrl,
}

impl Bus {
    /// Open an endpoint on the bus named by `url` with default options.
    pub async fn open(url: &str) -> Result<Bus, BusError> {
        Self::open_with(url, BusOptions::default()).await
    }

    /// Open an endpoint on the bus named by `url`, with a link of its own (see [`Interface`]
    /// for several endpoints on one link).
    pub async fn open_with(url: &str, options: BusOptions) -> Result<Bus, BusError> {
        Interface::open(url).await?.endpoint_with(options)
    }

    /// The URL this endpoint was opened with.
    pub fn url(&self) -> &BusUrl {
        &self.url
    }

    /// Send a frame (see [`BusSender::send`]).
    pub async fn send(&self, frame: Frame) -> Result<(), BusError> {
        self.sender.send(frame).await
    }

    /// Receive the next event (see [`BusReceiver::recv`]).
    pub async fn recv(&mut self) -> Option<BusEvent> {
        self.receiver.recv().await
    }

    /// Split into the sender and the receiver.
    pub fn split(self) -> (BusSender, BusReceiver) {
        (self.sender, self.receiver)
    }
}

/// A bus as a process reaches it — the link behind a URL — on which endpoints are opened, as
/// sockets are opened on a SocketCAN interface. Every endpoint of one `Interface` receives what
/// the others send (unless they filter it out) and everything else on the bus, through one link:
/// for `socketcand://` one TCP connection however many endpoints (a gateway's SDO client, its
/// own node, its supervision and its PDO feed would otherwise each hold one, and each frame on
/// the bus would cost each of them a read and a wake-up). The link lives while an endpoint or
/// a clone of the `Interface` does; it reconnects by itself, and every endpoint is told
/// ([`BusEvent::LinkDown`], [`BusEvent::LinkUp`]).
#[derive(Clone)]
pub struct Interface {
    url: BusUrl,
    link: Link,
}

#[derive(Clone)]
enum Link {
    Mem(String),
    Socketcand(socketcand::client::SharedLink),
    Socketcan(String),
}

impl Interface {
    /// Open the bus named by `url`: for `socketcand://` connect and complete the handshake now,
    /// so that a wrong address fails here.
    pub async fn open(url: &str) -> Result<Interface, BusError> {
        let parsed: BusUrl = url.parse()?;
        let link = match &parsed {
            BusUrl::Mem(name) => Link::Mem(name.clone()),
            BusUrl::Socketcand {
                host,
                port,
                channel,
            } => {
                Link::Socketcand(socketcand::client::SharedLink::open(host, *port, channel).await?)
            }
            BusUrl::Socketcan(iface) => Link::Socketcan(iface.clone()),
        };
        Ok(Interface { url: parsed, link })
    }

    /// A new endpoint with default options.
    pub fn endpoint(&self) -> Result<Bus, BusError> {
        self.endpoint_with(BusOptions::default())
    }

    /// A new endpoint on this interface.
    pub fn endpoint_with(&self, options: BusOptions) -> Result<Bus, BusError> {
        let (feed, receiver) = BusReceiver::channel(options.rx_queue);
        let sender = match &self.link {
            Link::Mem(name) => mem::open(name, feed, &options),
            Link::Socketcand(link) => link.endpoint(feed, &options),
            Link::Socketcan(iface) => crate::socketcan::open(iface, feed, &options)?,
        };
        Ok(Bus {
            sender,
            receiver,
            url: self.url.clone(),
        })
    }

    /// The URL this interface was opened with.
    pub fn url(&self) -> &BusUrl {
        &self.url
    }
}

impl fmt::Debug for Interface {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "Interface({})", self.url)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_parse_and_print() {
        let cases = [
            ("mem://lift", BusUrl::Mem("lift".into())),
            ("socketcan://can0", BusUrl::Socketcan("can0".into())),
            (
                "socketcand://127.0.0.1:29536/can0",
                BusUrl::Socketcand {
                    host: "127.0.0.1".into(),
                    port: 29536,
                    channel: "can0".into(),
                },
            ),
            (
                "socketcand://[::1]:1234/vcan0",
                BusUrl::Socketcand {
                    host: "::1".into(),
                    port: 1234,
                    channel: "vcan0".into(),
                },
            ),
        ];
        for (text, url) in cases {
            assert_eq!(text.parse::<BusUrl>().unwrap(), url);
            assert_eq!(url.to_string(), text);
        }
        let default_port: BusUrl = "socketcand://hub/can1".parse().unwrap();
        assert_eq!(default_port.to_string(), "socketcand://hub:29536/can1");
        for bad in [
            "can0",
            "mem://",
            "tcp://x/y",
            "socketcand://host:0/c",
            "socketcand://host:99999/c",
            "socketcand://host",
            "socketcand://:1/c",
            "socketcan://averyveryverylongname",
        ] {
            assert!(bad.parse::<BusUrl>().is_err(), "{bad}");
        }
    }
}
