//! Gateways on their WebSocket: one [`connection::Connection`] per gateway runs a portal
//! [`nxg::portal::Session`], checks the identity against the store, issues tokens, answers
//! operator requests through the [`Registry`] and stores and fans out notifications. A second
//! connection with a valid token replaces the first; a gateway that misbehaves is closed without
//! touching the others.

pub mod admissions;
pub mod connection;
mod dashboard;
pub mod local;
mod mailbox;
pub mod records;
pub mod refusals;
pub mod reports;
pub mod subscriptions;
pub mod telemetry;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use nxg::mplex::Mplex;
use nxg::msg::{self, Call, Method, Notification};
use nxg::portal::{Failure, Settings};
use serde_json::value::RawValue;
use tokio::sync::{broadcast, mpsc, oneshot};

use crate::config::Dashboard;
use cloud_cluster::msgs::HolderEntry;
use cloud_cluster::Cluster;
use cloud_store::Store;
use cloud_types::live::LiftEvent;

pub use connection::serve;
pub use telemetry::TelemetryCounters;

/// Up to `limit` queued items for a batch writer, into `batch`; 0 when there are no more.
/// Once `stop` turns true (the portal stops, its connections have ended) the queue takes
/// nothing new and what it holds is still handed out: the writer writes it and ends.
pub(crate) async fn next_batch<T>(
    rx: &mut mpsc::Receiver<T>,
    batch: &mut Vec<T>,
    limit: usize,
    stop: &mut tokio::sync::watch::Receiver<bool>,
) -> usize {
    if !*stop.borrow() {
        tokio::select! {
            n = rx.recv_many(batch, limit) => return n,
            Ok(_) = stop.wait_for(|stop| *stop) => {}
        }
    }
    rx.close();
    rx.recv_many(batch, limit).await
}

/// The answer to an operator request: the raw JSON of its `result`, or why not.
type Reply = oneshot::Sender<Result<String, Failure>>;

/// An operator request on its way to a gateway.
pub(crate) struct OperatorCall {
    method: Method,
    params: Option<Box<RawValue>>,
    reply: Reply,
}

/// Operator requests to a connection, and the order to close it.
pub(crate) type Calls = std::sync::Arc<mailbox::Mailbox<Box<OperatorCall>>>;

struct Live {
    calls: Calls,
    serial: u64,
    sernum: String,
    /// The domain token of its CONNECT: the account whose lift it is.
    domain: String,
    status: LiftStatus,
}

/// The error register (CiA 301 §7.5.2.2) of the lift controller.
pub const ERROR_REGISTER: Mplex = Mplex {
    index: 0x1001,
    sub: 0,
};
/// The lift state (CiA 417 5024h in our catalog: 4 is out of service).
pub const LIFT_STATE: Mplex = Mplex {
    index: 0x5024,
    sub: 0,
};
/// The lift state value of a lift out of service.
const OUT_OF_SERVICE: u8 = 4;

/// What the portal knows of a connected lift's condition from its pushes (the dashboard
/// subscribes to the error register and the lift state; a registration pushes the current
/// value first, docs/PROTOCOL.md §Subscriptions).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LiftStatus {
    /// The error register's bits, once pushed.
    pub error_register: Option<u8>,
    /// The lift state, once pushed.
    pub lift_state: Option<u8>,
    /// When the newest value arrived (ms since the epoch; 0: none yet).
    pub last_value: i64,
}

impl LiftStatus {
    /// Whether the error register reports a fault.
    pub fn faulty(&self) -> bool {
        self.error_register.is_some_and(|r| r != 0)
    }

    /// Whether the lift state is "out of service".
    pub fn out_of_service(&self) -> bool {
        self.lift_state == Some(OUT_OF_SERVICE)
    }
}

/// The gateways connected now, and the event channels of every lift; in a cluster, also
/// what the other processes hold ([`Cluster`]).
#[derive(Default)]
pub struct Registry {
    live: Mutex<HashMap<String, Live>>,
    events: Mutex<HashMap<String, broadcast::Sender<LiftEvent>>>,
    /// The newest connection epoch given out (µs since the Unix epoch, strictly rising).
    serial: AtomicU64,
    cluster: Option<Arc<Cluster>>,
    /// How long requests to gateways take (`canlift_gateway_round_trip_seconds`).
    round_trips: crate::metrics::Timer,
}

impl Registry {
    /// The registry of a process of `cluster` (lifts held elsewhere are reachable through it),
    /// or of a portal of its own.
    pub fn new(cluster: Option<Arc<Cluster>>, round_trips: crate::metrics::Timer) -> Registry {
        Registry {
            cluster,
            round_trips,
            ..Registry::default()
        }
    }

    /// The cluster this process is one of, if any.
    pub fn cluster(&self) -> Option<&Arc<Cluster>> {
        self.cluster.as_ref()
    }

    /// The holder entry of a lift another process of the cluster holds.
    fn elsewhere(&self, lift: &str) -> Option<HolderEntry> {
        self.cluster.as_ref()?.holder(lift)
    }

    /// `f` of the lift's connection to this process, if it has one.
    fn here<T>(&self, lift: &str, f: impl FnOnce(&Live) -> T) -> Option<T> {
        self.live
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(lift)
            .map(f)
    }

    /// Whether the lift's gateway is connected to this process.
    pub(crate) fn connected_here(&self, lift: &str) -> bool {
        self.here(lift, |_| ()).is_some()
    }

    /// The lift's connection now: a number that changes when its gateway reconnects, here or
    /// on another process of the cluster.
    pub fn connection(&self, lift: &str) -> Option<u64> {
        self.here(lift, |l| l.serial)
            .or_else(|| self.elsewhere(lift).map(|h| h.epoch))
    }

    /// Whether the lift's gateway is connected (here or to another process of the cluster).
    pub fn online(&self, lift: &str) -> bool {
        self.here(lift, |_| ()).is_some() || self.elsewhere(lift).is_some()
    }

    /// Whether `lift` is connected now as a lift of `domain`.
    pub fn serves(&self, domain: &str, lift: &str) -> bool {
        self.here(lift, |live| live.domain == domain)
            .unwrap_or_else(|| self.elsewhere(lift).is_some_and(|h| h.domain == domain))
    }

    /// How many gateways are connected to this process.
    pub fn online_count(&self) -> usize {
        self.live
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .len()
    }

    /// The serial number of a connected gateway (sent with puts and elevations).
    pub fn sernum(&self, lift: &str) -> Option<String> {
        self.here(lift, |l| l.sernum.clone())
            .or_else(|| self.elsewhere(lift).map(|h| h.sernum))
    }

    /// The condition of a connected lift (`None`: offline). Of a lift held by another
    /// process, the error register and lift state its holder last wrote, without the time.
    pub fn status(&self, lift: &str) -> Option<LiftStatus> {
        self.here(lift, |l| l.status).or_else(|| {
            self.elsewhere(lift).map(|h| LiftStatus {
                error_register: h.error_register,
                lift_state: h.lift_state,
                last_value: 0,
            })
        })
    }

    /// Take note of a pushed value of a connected lift, arrived at `at`.
    pub(crate) fn observe(&self, lift: &str, n: &Notification, at: i64) {
        let mut live = self.live.lock().unwrap_or_else(PoisonError::into_inner);
        let Some(status) = live.get_mut(lift).map(|l| &mut l.status) else {
            return;
        };
        status.last_value = at;
        if n.node.is_some() {
            return;
        }
        let value = n.value.trim().parse::<u8>().ok();
        match Mplex::parse(&n.mplex) {
            Ok(ERROR_REGISTER) => status.error_register = value,
            Ok(LIFT_STATE) => status.lift_state = value,
            _ => return,
        }
        if let Some(cluster) = self.cluster.as_ref() {
            cluster.status(lift, status.error_register, status.lift_state);
        }
    }

    /// Live events of a lift (in a cluster, also those its holder publishes from another
    /// process, from the moment NATS has this process's subscription and the holder its watch:
    /// at most a second).
    pub async fn subscribe(&self, lift: &str) -> broadcast::Receiver<LiftEvent> {
        let (rx, forwarding) = {
            let mut events = self.events.lock().unwrap_or_else(PoisonError::into_inner);
            let tx = events
                .entry(lift.to_owned())
                .or_insert_with(|| broadcast::channel(1024).0);
            let forwarding = self.cluster.as_ref().and_then(|c| c.forward(lift, tx));
            (tx.subscribe(), forwarding)
        };
        if let Some(subscribed) = forwarding {
            let _ = tokio::time::timeout(std::time::Duration::from_secs(1), subscribed).await;
        }
        rx
    }

    /// Hand `event` to the lift's live viewers. A channel exists only while someone watches
    /// (its 1024 slots are allocated up front: one per idle gateway would cost more than the
    /// connection itself).
    pub(crate) fn publish(&self, lift: &str, event: LiftEvent) {
        if let Some(cluster) = self.cluster.as_ref() {
            cluster.publish(lift, &event);
        }
        let mut events = self.events.lock().unwrap_or_else(PoisonError::into_inner);
        if let Some(tx) = events.get(lift) {
            if tx.send(event).is_err() {
                events.remove(lift);
            }
        }
    }

    /// Send `call` to the lift's gateway and wait for its answer.
    pub async fn call<C: Call>(&self, lift: &str, call: &C) -> Result<C::Answer, Failure> {
        let params =
            serde_json::value::to_raw_value(call).map_err(|e| Failure::Invalid(e.to_string()))?;
        let params = (params.get() != "null").then_some(params);
        let started = std::time::Instant::now();
        let raw = self.send(lift, C::METHOD, params).await;
        self.round_trips
            .observe(C::METHOD.name(), started.elapsed());
        msg::read::<C::Answer>(&raw?).map_err(Failure::Invalid)
    }

    /// Send a request to the lift's gateway: through its connection here, else (in a
    /// cluster) through the process holding it.
    async fn send(
        &self,
        lift: &str,
        method: Method,
        params: Option<Box<RawValue>>,
    ) -> Result<String, Failure> {
        let here = self.here(lift, |_| ()).is_some();
        match self.cluster.as_ref() {
            Some(cluster) if !here => {
                let call = cloud_cluster::msgs::RelayedCall {
                    method: method.name().into(),
                    params,
                };
                cluster
                    .request(lift, &cloud_cluster::msgs::Relayed::Call(call))
                    .await
            }
            _ => self.send_local(lift, method, params).await,
        }
    }

    /// Send a request to the lift's gateway through its connection on this process.
    pub(crate) async fn send_local(
        &self,
        lift: &str,
        method: Method,
        params: Option<Box<RawValue>>,
    ) -> Result<String, Failure> {
        let calls = self.here(lift, |l| l.calls.clone()).ok_or(Failure::Gone)?;
        let (reply, answer) = oneshot::channel();
        let call = Box::new(OperatorCall {
            method,
            params,
            reply,
        });
        calls.post(call).map_err(|e| match e {
            mailbox::Refused::Full(_) => Failure::Busy,
            mailbox::Refused::Ended(_) => Failure::Gone,
        })?;
        answer.await.map_err(|_| Failure::Gone)?
    }

    /// A new connection epoch: µs since the Unix epoch, above every earlier one of this
    /// process (so that across the cluster the newer connection of a lift has the larger).
    fn next_epoch(&self) -> u64 {
        let now = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| u64::try_from(d.as_micros()).unwrap_or(u64::MAX));
        let previous = self
            .serial
            .fetch_update(Ordering::Relaxed, Ordering::Relaxed, |last| {
                Some(now.max(last + 1))
            })
            .unwrap_or(now);
        now.max(previous + 1)
    }

    /// A connection is in service for `lift`: it replaces an earlier one (here, or in a
    /// cluster on any process). Returns the serial that [`Registry::unregister`] needs.
    fn register(&self, lift: &str, connect: &nxg::msg::Connect, calls: Calls) -> u64 {
        let serial = self.next_epoch();
        if let Some(cluster) = self.cluster.as_ref() {
            let entry = cluster.entry(
                serial,
                connect.domaintoken.clone(),
                connect.identity.sernum.clone(),
            );
            cluster.hold(lift, entry);
        }
        let old = self
            .live
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(
                lift.to_owned(),
                Live {
                    calls,
                    serial,
                    sernum: connect.identity.sernum.clone(),
                    domain: connect.domaintoken.clone(),
                    status: LiftStatus::default(),
                },
            );
        if let Some(old) = old {
            tracing::info!(lift, "a new connection replaces the old one");
            old.calls.close();
        }
        serial
    }

    /// Lift `lift` was retired (docs/PORTAL.md §Lifts and accounts): its gateway's connection
    /// to this process, if any, is closed; its next CONNECT is a first contact.
    pub fn retired(&self, lift: &str) {
        if let Some(live) = self
            .live
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get(lift)
        {
            live.calls.close();
        }
    }

    /// The connection `serial` of `lift` ended; whether it was still the lift's.
    fn unregister(&self, lift: &str, serial: u64) -> bool {
        let mut live = self.live.lock().unwrap_or_else(PoisonError::into_inner);
        if live.get(lift).is_some_and(|l| l.serial == serial) {
            live.remove(lift);
            if let Some(cluster) = self.cluster.as_ref() {
                cluster.release(lift, serial);
            }
            return true;
        }
        false
    }

    /// Another process of the cluster admitted a connection of `lift` (`newer`): the one
    /// here, if older, is closed without the lift going offline. Whether one was.
    pub(crate) fn taken_over(&self, lift: &str, newer: &HolderEntry) -> bool {
        let mut live = self.live.lock().unwrap_or_else(PoisonError::into_inner);
        let older = live.get(lift).is_some_and(|l| l.serial < newer.epoch);
        if !older {
            return false;
        }
        if let Some(old) = live.remove(lift) {
            tracing::info!(lift, node = %newer.node, "the lift connected to another portal process: closing it here");
            if let Some(cluster) = self.cluster.as_ref() {
                cluster.release(lift, old.serial);
            }
            old.calls.close();
        }
        true
    }
}

/// How the portal treats every gateway (`[gateways]`).
#[derive(Debug, Clone)]
pub struct Policy {
    /// Session settings.
    pub settings: Settings,
    /// Messages per second a gateway may send (`max_messages_per_s`).
    pub max_messages_per_s: u32,
    /// Longest value stored (`max_value_bytes`).
    pub max_value_bytes: usize,
    /// Bytes of values a lift may store per hour (`max_stored_bytes_per_hour`).
    pub max_stored_bytes_per_hour: u64,
    /// What a valid token from another board gets (`boardhash_change`).
    pub boardhash_change: crate::config::BoardhashChange,
    /// Tokens older than this are replaced at CONNECT (`token_rotate_days`).
    pub token_lifetime: Option<std::time::Duration>,
}

impl Policy {
    /// The policy of `[gateways]`.
    pub fn of(section: &crate::config::GatewaysSection) -> Policy {
        Policy {
            settings: section.settings(),
            max_messages_per_s: section.max_messages_per_s,
            max_value_bytes: section.max_value_bytes,
            max_stored_bytes_per_hour: section.max_stored_bytes_per_hour,
            boardhash_change: section.boardhash_change,
            token_lifetime: section.token_lifetime(),
        }
    }
}

/// What a connection task needs.
#[derive(Clone)]
pub struct Shared {
    /// The database.
    pub store: Store,
    /// Live gateways.
    pub registry: Arc<Registry>,
    /// How gateways are treated.
    pub policy: Policy,
    /// Where notifications go to be stored in batches (with its counters, for `/metrics`).
    pub telemetry: telemetry::Queue,
    /// Where CONNECTs are decided on, in batches.
    pub admissions: admissions::Admissions,
    /// Where the gateways' rows go to be written in batches.
    pub records: records::Records,
    /// What every gateway is asked to push (`live`, `inhibit_ms`, `events`), normalized.
    pub dashboard: Arc<Dashboard>,
    /// Who holds which subscriptions, registered again on every connection.
    pub subscriptions: Arc<subscriptions::Subscriptions>,
    /// What lift insights read: the state object's out-of-service values.
    pub insights: Arc<crate::config::Insights>,
    /// Where bus events and connection changes are reported (to become alarms).
    pub reports: reports::Reports,
    /// Where refused CONNECTs are recorded.
    pub refusals: Arc<refusals::Refusals>,
    /// Turns true when the portal stops: every connection closes.
    pub closing: tokio::sync::watch::Receiver<bool>,
}
