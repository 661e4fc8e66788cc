//! The portal as a cluster (docs/CLUSTER.md): several `canlift cloud` processes share one
//! PostgreSQL database and one NATS server. Which process holds which lift's gateway is a
//! JetStream KV entry per lift, written by its holder when it admits the connection and
//! standing while the holder's one lease in the same bucket is renewed; every process watches
//! the bucket (its view: `holders::Holders`). An operator request for a lift held elsewhere travels
//! as NATS request/reply on the lift's own subject, which only its holder subscribes to; live events
//! go out on the lift's events subject to whoever watches it on any process. Without NATS a
//! process goes on serving the gateways it holds, answers 503 for the others, and writes its
//! entries again when NATS is back.

#![warn(missing_docs)]

pub mod config;
mod events;
mod held;
mod holders;
pub mod msgs;
pub mod nats;
mod relay;

use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError, RwLock, Weak};
use std::time::{Duration, Instant};

use async_nats::jetstream::{self, kv};
use futures_util::StreamExt;
use nxg::msg::Method;
use nxg::portal::Failure;
use tokio::sync::{broadcast, mpsc, watch, Notify};

use cloud_types::live::LiftEvent;
use cloud_types::subscriptions::Terms;
use futures_util::future::BoxFuture;
use nxg::mplex::Mplex;
use serde_json::value::RawValue;

use cloud_types::subscriptions::Subscriber;
pub use config::ClusterSection;
use events::Leases;
use holders::Holders;
use msgs::{Alive, HolderEntry, Key};
use nats::{NatsAccess, NatsConfigError};

/// The result of a relayed hold or release the holder made (a JSON `null` would read back as
/// no result at all).
const DONE: &str = "true";

/// A holder's answer to a [`Relayed::Watch`] that found no lease of the watching process: it
/// holds none of that process's watchers' subscriptions (any more), so they are handed over.
const NEW_LEASE: &str = "false";

/// Live events waiting to be published; beyond this they are dropped and counted.
const EVENT_QUEUE: usize = 65_536;

/// How long a watching process waits for the holder to take its watch before it listens
/// anyway (no holder, or no NATS, answers at once).
const WATCH_ASK: Duration = Duration::from_secs(2);

/// What this process serves itself, as the cluster reaches it: the gateways connected here
/// and the subscriptions held on them (the portal's registry). Requests other processes relay
/// for lifts held here arrive through it, and it is told when a lift moves.
pub trait Local: Send + Sync {
    /// Another process admitted a connection of `lift` (`newer`): the one here, if older, is
    /// closed without the lift going offline. Whether one was.
    fn taken_over(&self, lift: &str, newer: &HolderEntry) -> bool;

    /// Send a request to the gateway of `lift` connected here, and wait for its answer (the
    /// raw JSON of its `result`).
    fn call<'a>(
        &'a self,
        lift: &'a str,
        method: Method,
        params: Option<Box<RawValue>>,
    ) -> BoxFuture<'a, Result<String, Failure>>;

    /// `subscriber` (of any process) asks for `objects` of `lift`, connected here, with `terms`.
    fn subscribe<'a>(
        &'a self,
        lift: &'a str,
        subscriber: &'a Subscriber,
        objects: &'a [Mplex],
        terms: Terms,
    ) -> BoxFuture<'a, Result<(), Failure>>;

    /// `subscriber` lets go of `objects` of `lift` (all of its own when `None`).
    fn unsubscribe<'a>(
        &'a self,
        lift: &'a str,
        subscriber: &'a Subscriber,
        objects: Option<&'a [Mplex]>,
    ) -> BoxFuture<'a, Result<(), Failure>>;

    /// The watchers of `process` let go of what they held of `lift` (their process's watch
    /// lapsed: it died, or lost NATS for too long).
    fn unsubscribe_process<'a>(&'a self, lift: &'a str, process: u64) -> BoxFuture<'a, ()>;

    /// Another process holds `lift` now, or its holder may have lost what this process's
    /// watchers asked for: hand their terms to it (in the background).
    fn moved(&self, lift: &str);

    /// This process's part of its watchers' ids ([`Subscriber::Watcher`]).
    fn process(&self) -> u64;
}

/// What `/metrics` shows of the cluster.
#[derive(Debug, Default)]
pub struct ClusterCounters {
    /// Operator requests sent to another process.
    pub relayed: AtomicU64,
    /// Of those, the ones that found no holder or no NATS (503) or timed out (504).
    pub relay_failed: AtomicU64,
    /// Requests of other processes answered for lifts held here.
    pub served: AtomicU64,
    /// Connections closed because their lift connected to another process.
    pub replaced: AtomicU64,
    /// Live events not published because the queue was full.
    pub events_dropped: AtomicU64,
    /// Live events of lifts held here not published because no other process watches them.
    pub events_unwatched: AtomicU64,
    /// Holder entries of processes that died, deleted by this one.
    pub swept: AtomicU64,
    /// Watches of lifts held here that lapsed unrenewed (per watching process and lift): that
    /// process's watchers' subscriptions were let go of.
    pub watch_lapsed: AtomicU64,
    /// Publications and subscriptions NATS refused (permissions violations).
    pub nats_refused: AtomicU64,
    /// Messages the NATS client dropped because a subscription here read too slowly (at
    /// least: the client reports a drop only while its own event queue has room).
    pub nats_slow: AtomicU64,
}

/// What went wrong with NATS since the client last connected.
#[derive(Default)]
struct Troubles {
    /// Why the last attempt to reach NATS failed (such as `authorization violation`).
    unreachable: Option<String>,
    /// The last publication or subscription NATS refused while connected: the NATS user lacks
    /// a permission the cluster needs (docs/CLUSTER.md §Securing NATS).
    refused: Option<String>,
    /// When NATS first refused a subscription since the client connected: NATS does not take
    /// it up by itself when the permission is granted later, the client subscribes again only
    /// when it connects again ([`Cluster::subscribe_again_when_refused`]).
    subscription_refused: Option<Instant>,
    /// The last slow consumer reported: logged once per subscription, not shown in `/healthz`
    /// (a drop is over when it is counted).
    slow: Option<String>,
}

/// This process's membership of the cluster.
pub struct Cluster {
    node: String,
    /// This life of the process ([`Alive`]).
    incarnation: u64,
    client: async_nats::Client,
    /// The bucket, once created on the NATS server (again after NATS restarts).
    kv: RwLock<Option<kv::Store>>,
    ttl: Duration,
    request_timeout: Duration,
    /// Copies of the bucket in a NATS cluster (`[cluster] nats_replicas`).
    replicas: usize,
    /// The other processes and the lifts they hold.
    holders: Mutex<Holders>,
    /// The lifts held here: dropping a sender ends its holder task.
    held: Mutex<HashMap<String, watch::Sender<HolderEntry>>>,
    /// The event forwarders running, by lift.
    forwarded: Mutex<HashMap<String, broadcast::Sender<LiftEvent>>>,
    /// Lifts held here that other processes watch: each watching process (its part of its
    /// watchers' ids) and until when its lease holds ([`Cluster::lease`]).
    watched: Mutex<Leases>,
    /// Poked on every connection event of the NATS client.
    nats_changed: Arc<Notify>,
    /// Raised each time the bucket is ready after connecting: holders write their entries
    /// again (a NATS server that restarted has none).
    generation: watch::Sender<u64>,
    events: mpsc::Sender<(String, Vec<u8>)>,
    /// Who holds which subscriptions here: told when a lift moves, asked by other processes.
    local: std::sync::OnceLock<Weak<dyn Local>>,
    /// What went wrong with NATS since the client last connected.
    troubles: Arc<Mutex<Troubles>>,
    /// Counted for `/metrics`.
    pub counters: Arc<ClusterCounters>,
}

impl Cluster {
    /// Connect to NATS as `node`. Returns at once: connecting, and connecting again after
    /// losing the server, go on in the background (a refusal, such as wrong credentials, is
    /// logged once per change and shown by [`Cluster::last_error`]). `request_timeout` bounds a
    /// relayed request (the holder's own timeout answers first).
    pub async fn connect(
        access: &NatsAccess,
        node: String,
        ttl: Duration,
        request_timeout: Duration,
        replicas: usize,
    ) -> Result<(Arc<Cluster>, mpsc::Receiver<(String, Vec<u8>)>), NatsConfigError> {
        let nats_changed = Arc::new(Notify::new());
        let troubles = Arc::new(Mutex::new(Troubles::default()));
        let counters = Arc::new(ClusterCounters::default());
        let (poke, name, noted, counted) = (
            nats_changed.clone(),
            node.clone(),
            troubles.clone(),
            counters.clone(),
        );
        let options = access
            .options()
            .name(format!("canlift portal {node}"))
            .retry_on_initial_connect()
            .connection_timeout(Duration::from_secs(2))
            // The first attempt at once (at start, and when the server is lost: another of a
            // NATS cluster may be there), then every 0.25 s more, up to 2 s.
            .reconnect_delay_callback(|attempts| {
                Duration::from_millis((250 * attempts.saturating_sub(1) as u64).min(2_000))
            })
            .event_callback(move |event| {
                let (poke, name, noted, counted) =
                    (poke.clone(), name.clone(), noted.clone(), counted.clone());
                async move {
                    on_event(&event, &name, &noted, &counted);
                    poke.notify_waiters();
                }
            });
        // With `retry_on_initial_connect` this returns at once; it fails only on an address
        // that `NatsAccess` already parsed.
        let client = options
            .connect(access.servers())
            .await
            .map_err(|e| access.error(e.to_string()))?;
        let (events, events_rx) = mpsc::channel(EVENT_QUEUE);
        let ttl = ttl.max(Duration::from_secs(3));
        let cluster = Arc::new(Cluster {
            holders: Mutex::new(Holders::new(&node, ttl, Instant::now())),
            node,
            incarnation: rand::random(),
            client,
            kv: RwLock::new(None),
            ttl,
            request_timeout,
            replicas,
            held: Mutex::default(),
            forwarded: Mutex::default(),
            watched: Mutex::default(),
            nats_changed,
            generation: watch::channel(0).0,
            events,
            local: std::sync::OnceLock::new(),
            troubles,
            counters,
        });
        Ok((cluster, events_rx))
    }

    /// This process's name.
    pub fn node(&self) -> &str {
        &self.node
    }

    /// Whether NATS is reachable now.
    pub fn connected(&self) -> bool {
        self.client.connection_state() == async_nats::connection::State::Connected
    }

    /// Why the last attempt to reach NATS failed (such as `authorization violation`), while it
    /// is not reached again.
    pub fn last_error(&self) -> Option<String> {
        lock(&self.troubles).unreachable.clone()
    }

    /// The last publication or subscription NATS refused since the client connected (a
    /// permissions violation: part of the cluster's work fails while the NATS user lacks it).
    pub fn refused(&self) -> Option<String> {
        lock(&self.troubles).refused.clone()
    }

    /// How many lifts are held here.
    pub fn held_count(&self) -> usize {
        lock(&self.held).len()
    }

    /// How many lifts other processes hold, as far as this one knows.
    pub fn known_count(&self) -> usize {
        lock(&self.holders).held_elsewhere(Instant::now())
    }

    /// How many processes of the cluster live, this one included (as far as it knows).
    pub fn processes(&self) -> usize {
        1 + lock(&self.holders).others_alive(Instant::now())
    }

    /// The holder entry of a lift another process holds (`None`: not held elsewhere, or its
    /// holder's lease lapsed: the holder died).
    pub fn holder(&self, lift: &str) -> Option<HolderEntry> {
        lock(&self.holders).holder(lift, Instant::now()).cloned()
    }

    fn kv(&self) -> Option<kv::Store> {
        self.kv
            .read()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Wait until NATS's connection state may have changed (at most half a second).
    /// Serve `local`: the gateways connected to this process and the subscriptions held on
    /// them, which requests relayed by other processes reach and which are told when a lift
    /// moves. Given once, before [`Cluster::run`]; held weakly (it holds the cluster).
    pub fn serve(&self, local: Weak<dyn Local>) {
        let _ = self.local.set(local);
    }

    fn local(&self) -> Option<Arc<dyn Local>> {
        self.local.get().and_then(Weak::upgrade)
    }

    /// How long a holder publishes a lift's live events, and keeps the subscriptions of the
    /// watchers of a process, after that process last asked ([`Relayed::Watch`]): twice the
    /// holder TTL (`[cluster] holder_ttl_s`), six renewals.
    fn lease(&self) -> Duration {
        self.ttl * 2
    }

    /// How often a process renews its watches, and learns that nobody on it watches a
    /// forwarded lift any more.
    fn renewal(&self) -> Duration {
        self.ttl / 3
    }

    async fn nats_event(&self) {
        let _ =
            tokio::time::timeout(Duration::from_millis(500), self.nats_changed.notified()).await;
    }

    /// Keep the bucket and this process's view of it: create the bucket whenever NATS is
    /// (again) reachable, renew this process's lease, then follow every entry until the
    /// connection is lost.
    pub async fn run(self: Arc<Self>) {
        tokio::spawn(self.clone().every_renewal());
        tokio::spawn(self.clone().subscribe_again_when_refused());
        let js = jetstream::new(self.client.clone());
        // The bucket's stream as the KV convention (NATS ADR-8) lays it out, created directly:
        // `create_key_value` first reads the account's information, which it cannot parse
        // from the NATS 2.9 of Debian 12. No age limit: an entry stands while its holder's
        // lease does, and the entries of a process that died are deleted by a living one.
        let config = jetstream::stream::Config {
            name: format!("KV_{}", msgs::BUCKET),
            subjects: vec![format!("$KV.{}.>", msgs::BUCKET)],
            max_messages_per_subject: 1,
            storage: jetstream::stream::StorageType::Memory,
            discard: jetstream::stream::DiscardPolicy::New,
            allow_rollup: true,
            deny_delete: true,
            allow_direct: true,
            num_replicas: self.replicas,
            ..Default::default()
        };
        // Whether the connection was (re)made since the holders last wrote their entries: the
        // first time, and after NATS was lost (it may have restarted, with an empty bucket). A
        // watch interrupted on a live connection (a slow consumer) needs no rewrite.
        let mut reconnected = true;
        loop {
            if !self.connected() {
                reconnected = true;
                self.nats_event().await;
                continue;
            }
            let bucket = match js.get_or_create_stream(config.clone()).await {
                Ok(stream) => {
                    let copies = stream.cached_info().config.num_replicas;
                    if copies < self.replicas {
                        // A NATS grown into a cluster: the bucket gains copies in place, its
                        // entries kept. Only ever more: processes configured apart during a
                        // rolling change would otherwise take turns; the largest wish stands.
                        let more = jetstream::stream::Config {
                            num_replicas: self.replicas,
                            ..stream.cached_info().config.clone()
                        };
                        match js.update_stream(more).await {
                            Ok(_) => tracing::info!(
                                copies = self.replicas,
                                before = copies,
                                "NATS: the holder bucket keeps more copies"
                            ),
                            Err(e) => tracing::warn!(
                                error = %e,
                                copies,
                                nats_replicas = self.replicas,
                                "NATS: the holder bucket keeps the copies it has"
                            ),
                        }
                    } else if copies > self.replicas {
                        tracing::warn!(
                            copies,
                            nats_replicas = self.replicas,
                            "NATS: the holder bucket keeps its copies (a process only ever asks for more)"
                        );
                    }
                    js.get_key_value(msgs::BUCKET)
                        .await
                        .map_err(|e| e.to_string())
                }
                Err(e) => Err(e.to_string()),
            };
            let store = match bucket {
                Ok(store) => store,
                Err(e) => {
                    tracing::warn!(error = %e, "NATS: no holder bucket");
                    tokio::time::sleep(Duration::from_secs(1)).await;
                    continue;
                }
            };
            *self.kv.write().unwrap_or_else(PoisonError::into_inner) = Some(store.clone());
            // The lease before the entries: other processes take them for held once it is there.
            // A bucket just made in a NATS cluster may not take writes yet: try again soon, not
            // a renewal period later.
            if !self.renew(&store).await {
                tokio::time::sleep(Duration::from_secs(1)).await;
                continue;
            }
            if std::mem::take(&mut reconnected) {
                self.generation.send_modify(|g| *g += 1);
            }
            lock(&self.holders).rewatch(Instant::now());
            let mut catching_up = true;
            // Every key's last entry first (`watch_all` would deliver only what is written
            // from now on), then each change.
            match store.watch_with_history(">").await {
                Ok(mut entries) => loop {
                    tokio::select! {
                        entry = entries.next() => match entry {
                            Some(Ok(entry)) => {
                                // The first entry past the bucket's contents when the watch
                                // began (there is one: this process's lease).
                                let current = entry.seen_current;
                                self.learn(entry);
                                if current && std::mem::take(&mut catching_up) {
                                    lock(&self.holders).caught_up();
                                }
                            }
                            Some(Err(e)) => {
                                tracing::warn!(error = %e, "NATS: holder entries interrupted");
                                break;
                            }
                            None => break,
                        },
                        _ = self.nats_event() => if !self.connected() { break },
                    }
                },
                Err(e) => tracing::warn!(error = %e, "NATS: cannot follow holder entries"),
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
    }

    /// Every third of the TTL: while NATS is reachable, renew this process's lease and delete
    /// what dead processes left; in any case let go of the subscriptions of watching processes
    /// whose watch lapsed (also while NATS is unreachable: then no process can renew its watch).
    async fn every_renewal(self: Arc<Self>) {
        let mut tick = tokio::time::interval(self.renewal());
        loop {
            tick.tick().await;
            if let Some(kv) = self.kv().filter(|_| self.connected()) {
                let _ = self.renew(&kv).await;
                self.sweep(&kv);
            }
            let lapsed = lock(&self.watched).lapsed_all(Instant::now());
            for (lift, processes) in lapsed {
                self.release_lapsed(lift, processes);
            }
        }
    }

    /// While NATS refuses a subscription of this process, connect again now and then: a NATS
    /// whose configuration was mended and reloaded (`nats-server --signal reload`) keeps the
    /// connection with the new permissions but does not take up a subscription it refused, and
    /// the client sends its subscriptions again only on connecting (docs/CLUSTER.md §Securing
    /// NATS). Each attempt that is refused again waits longer ([`resubscribe_delay`]).
    async fn subscribe_again_when_refused(self: Arc<Self>) {
        let mut attempts = 0;
        let mut last_refused: Option<Instant> = None;
        loop {
            // Armed before the look, so that a refusal reported in between still wakes this
            // task; nothing else does while NATS refuses nothing.
            let event = self.nats_changed.notified();
            tokio::pin!(event);
            event.as_mut().enable();
            let Some(since) = lock(&self.troubles).subscription_refused else {
                event.await;
                continue;
            };
            // Refused again after quiet minutes: the permissions were mended in between.
            if last_refused.is_some_and(|t| t.elapsed() > RESUBSCRIBE_MAX * 2) {
                attempts = 0;
            }
            last_refused = Some(Instant::now());
            let due = since + resubscribe_delay(attempts);
            if Instant::now() < due {
                tokio::select! {
                    _ = event => {}
                    _ = tokio::time::sleep_until(due.into()) => {}
                }
                continue;
            }
            tracing::info!(
                attempt = attempts + 1,
                "NATS refused a subscription: connecting again to subscribe again (a permission granted meanwhile takes effect)"
            );
            attempts += 1;
            lock(&self.troubles).subscription_refused = None;
            if self.client.force_reconnect().await.is_err() {
                return;
            }
        }
    }

    /// Write this process's lease; whether NATS took it.
    async fn renew(&self, kv: &kv::Store) -> bool {
        let alive = Alive {
            incarnation: self.incarnation,
        };
        let Ok(value) = serde_json::to_vec(&alive) else {
            return false;
        };
        let key = Key::Process(self.node.clone()).encode();
        match kv.put(key, value.into()).await {
            Ok(_) => true,
            Err(e) => {
                tracing::warn!(error = %e, "NATS: lease not renewed");
                false
            }
        }
    }

    /// Delete the entries left of processes that died, when this process is the one that
    /// sweeps ([`Holders::suspects`]), each at the revision it saw (a lift that connected again
    /// meanwhile keeps its new entry). A suspect's lease is read from the bucket first: a view
    /// behind the bucket took living processes for dead, and under load its sweeps deleted
    /// their entries faster than they wrote them again.
    fn sweep(self: &Arc<Self>, kv: &kv::Store) {
        let suspects = lock(&self.holders).suspects(Instant::now());
        if suspects.is_empty() {
            return;
        }
        let (kv, cluster) = (kv.clone(), self.clone());
        tokio::spawn(async move {
            let mut checked = Vec::with_capacity(suspects.len());
            for (node, incarnation) in suspects {
                let Ok(lease) = kv.entry(Key::Process(node.clone()).encode()).await else {
                    // Not known now: asked again at the next renewal.
                    continue;
                };
                if let Some(entry) = lease.filter(|e| e.operation == kv::Operation::Put) {
                    cluster.learn(entry);
                }
                checked.push((node, incarnation));
            }
            let dead = lock(&cluster.holders).sweep(Instant::now(), &checked);
            if dead.is_empty() {
                return;
            }
            tracing::info!(
                entries = dead.len(),
                "NATS: deleting the holder entries of processes that died"
            );
            for (lift, revision) in dead {
                let key = Key::Lift(lift).encode();
                if kv.delete_expect_revision(key, Some(revision)).await.is_ok() {
                    cluster.counters.swept.fetch_add(1, Ordering::Relaxed);
                }
            }
        });
    }

    /// An entry changed. Another process's lease: noted. Another process's entry of a lift:
    /// remembered; if it is of a newer connection than one held here, that one is closed (the
    /// gateway moved), if of an older one, the holder here writes its entry again. This
    /// process's own entry that is not of a connection it holds (left from before NATS was
    /// lost, or from an earlier life): deleted.
    fn learn(self: &Arc<Self>, entry: kv::Entry) {
        let lift = match Key::decode(&entry.key) {
            Some(Key::Lift(lift)) => lift,
            Some(Key::Process(node)) => {
                if entry.operation == kv::Operation::Put {
                    if let Ok(alive) = serde_json::from_slice::<Alive>(&entry.value) {
                        let written = self.written(&entry);
                        lock(&self.holders).lease(&node, alive.incarnation, written);
                    }
                }
                return;
            }
            None => return,
        };
        if entry.operation != kv::Operation::Put {
            lock(&self.holders).remove(&lift);
            // Deleted while held here (by a sweep that took this process for dead): again.
            self.rewrite(&lift);
            return;
        }
        let Ok(held) = serde_json::from_slice::<HolderEntry>(&entry.value) else {
            tracing::warn!(%lift, "NATS: a holder entry that is not one");
            return;
        };
        if held.node == self.node {
            lock(&self.holders).remove(&lift);
            let ours = lock(&self.held).get(&lift).map(|h| h.borrow().epoch);
            match ours {
                Some(epoch) if epoch == held.epoch && held.incarnation == self.incarnation => {}
                Some(_) => self.rewrite(&lift),
                None => self.delete_stale(&entry),
            }
            return;
        }
        if let Some(local) = self.local() {
            if local.taken_over(&lift, &held) {
                self.counters.replaced.fetch_add(1, Ordering::Relaxed);
            } else {
                // An older connection's late entry over the one of a lift held here.
                self.rewrite(&lift);
            }
        }
        let connection = (held.node.clone(), held.epoch);
        let before = lock(&self.holders).put(&lift, held, entry.revision);
        // A new connection (not a status change): the watchers here ask its holder for their
        // live events and their objects — the objects when the holder answers that the watch
        // is new to it, which a new holder always does (one hand-over per move, not two).
        if before.is_none_or(|b| (b.node, b.epoch) != connection) {
            if lock(&self.forwarded).contains_key(&lift) {
                tokio::spawn(self.clone().ask_to_publish(lift));
            } else if let Some(local) = self.local() {
                local.moved(&lift);
            }
        }
    }

    /// When an entry was written, by its age as the NATS server tells it (clamped to the TTL:
    /// older is as good as expired).
    fn written(&self, entry: &kv::Entry) -> Instant {
        let age = (time::OffsetDateTime::now_utc() - entry.created).clamp(
            time::Duration::ZERO,
            time::Duration::try_from(self.ttl).unwrap_or(time::Duration::ZERO),
        );
        Instant::now()
            .checked_sub(Duration::try_from(age).unwrap_or_default())
            .unwrap_or_else(Instant::now)
    }

    /// The holder of `lift` here, if any, writes its entry again (over what it finds).
    fn rewrite(&self, lift: &str) {
        if let Some(held) = lock(&self.held).get(lift) {
            held.send_modify(|_| {});
        }
    }

    /// Delete an entry of this process that is of no connection it holds.
    fn delete_stale(&self, entry: &kv::Entry) {
        let Some(kv) = self.kv() else {
            return;
        };
        let (key, revision) = (entry.key.clone(), entry.revision);
        tokio::spawn(async move {
            let _ = kv.delete_expect_revision(key, Some(revision)).await;
        });
    }
}

/// What the NATS client reports, kept for `/healthz` and counted for `/metrics`.
fn on_event(
    event: &async_nats::Event,
    node: &str,
    troubles: &Mutex<Troubles>,
    counters: &ClusterCounters,
) {
    use async_nats::{Event, ServerError};
    match event {
        Event::Connected => {
            *lock(troubles) = Troubles::default();
            tracing::info!(node, "NATS connected")
        }
        Event::Disconnected => {
            tracing::warn!(node, "NATS unreachable: serving the lifts held here only")
        }
        Event::ServerError(ServerError::Other(e))
            if e.to_ascii_lowercase().starts_with("permissions violation") =>
        {
            counters.nats_refused.fetch_add(1, Ordering::Relaxed);
            let mut troubles = lock(troubles);
            note(&mut troubles.refused, node, e.clone());
            if e.to_ascii_lowercase().contains(" for subscription ") {
                troubles
                    .subscription_refused
                    .get_or_insert_with(Instant::now);
            }
        }
        // A message dropped because its subscription's queue was full (a relayed request then
        // times out, a watcher misses an event, the fleet's watch starts again): the process
        // does not keep up with what NATS brings it.
        Event::SlowConsumer(_) => {
            counters.nats_slow.fetch_add(1, Ordering::Relaxed);
            note(&mut lock(troubles).slow, node, event.to_string());
        }
        Event::ClientError(e) => note(&mut lock(troubles).unreachable, node, e.to_string()),
        Event::ServerError(e @ (ServerError::AuthorizationViolation | ServerError::Other(_))) => {
            note(&mut lock(troubles).unreachable, node, e.to_string())
        }
        other => tracing::debug!(node, event = %other, "NATS"),
    }
}

/// Keep the NATS client's error for `/healthz`; every failed attempt reports it again, so it is
/// logged only when it changes.
/// `error` kept in `last`, and logged unless it is what `last` already held.
fn note(last: &mut Option<String>, node: &str, error: String) {
    let error = error.trim_start_matches("nats: ").to_owned();
    if last.as_deref() != Some(error.as_str()) {
        tracing::warn!(node, %error, "NATS");
        *last = Some(error);
    }
}

/// The longest wait between two connections made to have a refused subscription taken up.
const RESUBSCRIBE_MAX: Duration = Duration::from_secs(60);

/// How long after NATS refused a subscription the client connects again, `attempts` connections
/// after the first refusal: 5 s, then twice as long each time, at most [`RESUBSCRIBE_MAX`] —
/// a permission mended is in force within a minute, and a NATS still refusing is not made to
/// take every subscription of the process again every few seconds.
fn resubscribe_delay(attempts: u32) -> Duration {
    Duration::from_secs(5)
        .saturating_mul(1 << attempts.min(8))
        .min(RESUBSCRIBE_MAX)
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refused_subscription_is_asked_for_again_ever_less_often() {
        let delays: Vec<u64> = (0..6).map(|a| resubscribe_delay(a).as_secs()).collect();
        assert_eq!(delays, [5, 10, 20, 40, 60, 60]);
        assert_eq!(resubscribe_delay(u32::MAX), RESUBSCRIBE_MAX);
    }

    #[test]
    fn only_a_refused_subscription_makes_the_client_connect_again() {
        use async_nats::{Event, ServerError};
        let (troubles, counters) = (Mutex::new(Troubles::default()), ClusterCounters::default());
        let report = |e: &str| {
            let event = Event::ServerError(ServerError::Other(e.into()));
            on_event(&event, "p0", &troubles, &counters)
        };
        report("Permissions Violation for Publish to \"canlift.lift.L.events\"");
        assert!(lock(&troubles).refused.is_some());
        assert!(
            lock(&troubles).subscription_refused.is_none(),
            "a publication is simply refused again next time"
        );
        report("Permissions Violation for Subscription to \"canlift.lift.L.rpc\"");
        let first = lock(&troubles).subscription_refused;
        assert!(first.is_some());
        report("Permissions Violation for Subscription to \"canlift.lift.M.rpc\"");
        assert_eq!(
            lock(&troubles).subscription_refused,
            first,
            "counted from the first refusal"
        );
        on_event(&Event::Connected, "p0", &troubles, &counters);
        assert!(lock(&troubles).subscription_refused.is_none());
    }

    #[test]
    fn what_nats_reports_is_counted_and_kept_for_health() {
        use async_nats::{Event, ServerError};
        let (troubles, counters) = (Mutex::new(Troubles::default()), ClusterCounters::default());
        let report = |event: Event| on_event(&event, "p0", &troubles, &counters);
        report(Event::ServerError(ServerError::AuthorizationViolation));
        report(Event::ServerError(ServerError::Other(
            "Permissions Violation for Subscription to \"canlift.lift.L.rpc\"".into(),
        )));
        for sid in [7, 7, 9] {
            report(Event::SlowConsumer(sid));
        }
        let count = |counter: &AtomicU64| counter.load(Ordering::Relaxed);
        assert_eq!(count(&counters.nats_refused), 1);
        assert_eq!(count(&counters.nats_slow), 3);
        {
            let troubles = lock(&troubles);
            assert_eq!(
                troubles.unreachable.as_deref(),
                Some("authorization violation")
            );
            assert!(troubles
                .refused
                .as_deref()
                .is_some_and(|e| e.contains("canlift.lift.L.rpc")));
            // A drop is counted, not kept as the process's state.
            assert_eq!(
                troubles.slow.as_deref(),
                Some("slow consumers for subscription 9")
            );
        }
        report(Event::Connected);
        let troubles = lock(&troubles);
        assert!(troubles.unreachable.is_none() && troubles.refused.is_none());
        assert_eq!(count(&counters.nats_slow), 3);
    }
}
