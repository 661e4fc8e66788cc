//! Subscriptions that belong to someone (docs/PORTAL.md §Subscriptions), sans-IO.
//!
//! A gateway keeps one subscription per object (NXg §7.3: a second `reg_canopen_object` for an
//! object replaces the first's inhibit and threshold; `unreg_canopen_object` ends it for
//! everyone). Several parties at the portal want pushes of one lift — the dashboard on every
//! lift, a user through the API, each live watcher — so the portal keeps who holds what and
//! registers with the gateway the union: per object the smallest inhibit and the smallest
//! threshold of its subscribers. An object leaves the gateway only when its last subscriber lets go, and
//! after a reconnect everything held is registered again.
//!
//! The dashboard's objects are the same on every lift: they are the [`DashboardTerms`] of each lift's
//! [`Subscribers`] rather than an entry per lift, so an idle lift costs nothing here.
//!
//! Users' subscriptions are in the database (the API writes them): the process the gateway
//! connects to — after a portal restart, or another process of a cluster — reads them at
//! CONNACK. In a cluster (docs/CLUSTER.md §Subscriptions) the lift's holder (the process its
//! gateway is connected to) keeps the terms of every subscriber on any process and registers
//! the union; another process relays its subscribers' requests there and hands its own watchers' terms to each new holder of the lift.

use std::collections::{BTreeMap, HashMap};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use cloud_types::subscriptions::{Subscriber, Terms};
use nxg::mplex::Mplex;
use nxg::msg::{RegParams, UnregParams};
use nxg::portal::Failure;

use super::Registry;
use crate::config::Dashboard;
use cloud_cluster::msgs::{Relayed, RelayedHold, RelayedRelease};
use cloud_cluster::Cluster;
use cloud_store::Store;

/// The objects every lift holds for the dashboard, with their terms.
pub type DashboardTerms = BTreeMap<Mplex, Terms>;

/// What to send to the gateway.
#[derive(Debug, Clone, PartialEq)]
pub enum Change {
    /// `reg_canopen_object` for these objects with these terms.
    Register(Vec<Mplex>, Terms),
    /// `unreg_canopen_object` for these objects.
    Unregister(Vec<Mplex>),
}

/// The subscribers of one lift's objects beyond the dashboard.
#[derive(Debug, Clone, Default)]
pub struct Subscribers {
    objects: BTreeMap<Mplex, BTreeMap<Subscriber, Terms>>,
}

impl Subscribers {
    /// `subscriber` asks for `objects` with `terms` (replacing what it asked for them before).
    pub fn add(
        &mut self,
        base: &DashboardTerms,
        subscriber: &Subscriber,
        objects: &[Mplex],
        terms: Terms,
    ) -> Vec<Change> {
        let before = self.unions(base, objects);
        for mplex in objects {
            self.objects
                .entry(*mplex)
                .or_default()
                .insert(subscriber.clone(), terms);
        }
        self.changes(base, before)
    }

    /// `subscriber` lets go of `objects` (all of its own when `None`); what it did not hold is
    /// left alone.
    pub fn remove(
        &mut self,
        base: &DashboardTerms,
        subscriber: &Subscriber,
        objects: Option<&[Mplex]>,
    ) -> Vec<Change> {
        let objects: Vec<Mplex> = match objects {
            Some(list) => list.to_vec(),
            None => self
                .objects
                .iter()
                .filter(|(_, subscribers)| subscribers.contains_key(subscriber))
                .map(|(mplex, _)| *mplex)
                .collect(),
        };
        let before = self.unions(base, &objects);
        for mplex in &objects {
            if let Some(subscribers) = self.objects.get_mut(mplex) {
                subscribers.remove(subscriber);
                if subscribers.is_empty() {
                    self.objects.remove(mplex);
                }
            }
        }
        self.changes(base, before)
    }

    /// Every subscriber `which` says yes to lets go of all it holds.
    pub fn remove_where(
        &mut self,
        base: &DashboardTerms,
        which: impl Fn(&Subscriber) -> bool,
    ) -> Vec<Change> {
        let objects: Vec<Mplex> = self
            .objects
            .iter()
            .filter(|(_, subscribers)| subscribers.keys().any(&which))
            .map(|(mplex, _)| *mplex)
            .collect();
        let before = self.unions(base, &objects);
        self.retain(|subscriber| !which(subscriber));
        self.changes(base, before)
    }

    /// Everything held, for a gateway that has just connected (the dashboard's objects too).
    pub fn all(&self, base: &DashboardTerms) -> Vec<Change> {
        let objects: Vec<Mplex> = base.keys().chain(self.objects.keys()).copied().collect();
        let before = objects.iter().map(|m| (*m, None)).collect();
        self.changes(base, before)
    }

    /// Whether no one beyond the dashboard holds anything.
    pub fn is_empty(&self) -> bool {
        self.objects.is_empty()
    }

    /// Forget every subscriber `keep` says no to, without any change at the gateway (for a lift
    /// whose connection here ended, or that moved to another process).
    pub fn retain(&mut self, keep: impl Fn(&Subscriber) -> bool) {
        self.objects.retain(|_, subscribers| {
            subscribers.retain(|subscriber, _| keep(subscriber));
            !subscribers.is_empty()
        });
    }

    /// What each subscriber asks for, grouped by terms: one request per subscriber and terms.
    pub fn requests(&self) -> Vec<(Subscriber, Terms, Vec<Mplex>)> {
        let mut requests: Vec<(Subscriber, Terms, Vec<Mplex>)> = Vec::new();
        for (mplex, subscribers) in &self.objects {
            for (subscriber, terms) in subscribers {
                match requests
                    .iter_mut()
                    .find(|(h, t, _)| h == subscriber && t == terms)
                {
                    Some((_, _, list)) => list.push(*mplex),
                    None => requests.push((subscriber.clone(), *terms, vec![*mplex])),
                }
            }
        }
        requests
    }

    /// The terms registered for `mplex` (the union of its subscribers'), if anyone holds it.
    fn union(&self, base: &DashboardTerms, mplex: &Mplex) -> Option<Terms> {
        let held = self.objects.get(mplex).into_iter().flat_map(|h| h.values());
        base.get(mplex)
            .into_iter()
            .chain(held)
            .copied()
            .reduce(Terms::union)
    }

    fn unions(&self, base: &DashboardTerms, objects: &[Mplex]) -> BTreeMap<Mplex, Option<Terms>> {
        objects.iter().map(|m| (*m, self.union(base, m))).collect()
    }

    /// The gateway calls that take each object from its `before` union to its union now:
    /// registrations grouped by terms (one call per distinct terms), then one unregistration.
    fn changes(
        &self,
        base: &DashboardTerms,
        before: BTreeMap<Mplex, Option<Terms>>,
    ) -> Vec<Change> {
        let mut register: Vec<(Terms, Vec<Mplex>)> = Vec::new();
        let mut unregister = Vec::new();
        for (mplex, was) in before {
            match (was, self.union(base, &mplex)) {
                (Some(_), None) => unregister.push(mplex),
                (was, Some(now)) if was != Some(now) => {
                    match register.iter_mut().find(|(terms, _)| *terms == now) {
                        Some((_, list)) => list.push(mplex),
                        None => register.push((now, vec![mplex])),
                    }
                }
                _ => {}
            }
        }
        let mut changes: Vec<Change> = register
            .into_iter()
            .map(|(terms, list)| Change::Register(list, terms))
            .collect();
        if !unregister.is_empty() {
            changes.push(Change::Unregister(unregister));
        }
        changes
    }
}

/// Every lift's subscribers with the dashboard's terms, and the gateway calls that keep each gateway
/// at the union. The changes of one lift are made one at a time — computed, sent, then kept —
/// so its gateway sees them in the order they were made, and a change the gateway refused is
/// not kept.
pub struct Subscriptions {
    registry: Arc<Registry>,
    store: Store,
    base: DashboardTerms,
    lifts: Mutex<HashMap<String, Arc<tokio::sync::Mutex<Subscribers>>>>,
    /// Objects beyond the dashboard's asked of each lift's gateway now: what its pushes may be
    /// of ([`Subscriptions::wanted`]). Taken in before the gateway is asked (a registration
    /// pushes the current value at once), let go of once it confirmed an unregistration.
    asked: Mutex<HashMap<String, std::collections::HashSet<Mplex>>>,
    /// This process's part of its watchers' ids (the upper 32 bits).
    process: u64,
    watchers: AtomicU64,
}

/// Whether a change for a lift whose gateway is offline is kept (for a live watcher: it is
/// registered when the gateway connects) or refused (an API call answers 503).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum WhenOffline {
    /// Keep it.
    Keep,
    /// Refuse it.
    Refuse,
}

impl Subscriptions {
    /// No one holds anything yet; every lift holds the dashboard's objects, and the users'
    /// subscriptions in `store` once its gateway connects.
    pub fn new(registry: Arc<Registry>, store: Store, dashboard: &Dashboard) -> Subscriptions {
        let terms = Terms {
            inhibit: dashboard.inhibit_ms,
            threshold: 0.0,
        };
        Subscriptions {
            registry,
            store,
            base: dashboard.live.iter().map(|m| (*m, terms)).collect(),
            lifts: Mutex::default(),
            asked: Mutex::default(),
            process: u64::from(rand::random::<u32>()) << 32,
            watchers: AtomicU64::new(1),
        }
    }

    /// Whether `lift`'s gateway was asked to push `mplex` (of the lift controller): the
    /// dashboard's objects, and those someone subscribed to.
    pub fn wanted(&self, lift: &str, mplex: Mplex) -> bool {
        self.base.contains_key(&mplex)
            || self
                .asked
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .get(lift)
                .is_some_and(|set| set.contains(&mplex))
    }

    /// A subscriber for a new live watcher.
    pub fn watcher(&self) -> Subscriber {
        let serial = self.watchers.fetch_add(1, Ordering::Relaxed) & u64::from(u32::MAX);
        Subscriber::Watcher(self.process | serial)
    }

    /// Whether `subscriber` is a watcher of this process (its terms stay here when the lift's
    /// connection ends or moves; users' are in the database, other processes' with them).
    fn own(&self, subscriber: &Subscriber) -> bool {
        subscriber.process() == Some(self.process)
    }

    /// This process's part of its watchers' ids (see [`Subscriber::process`]).
    pub(crate) fn process(&self) -> u64 {
        self.process
    }

    /// The cluster, when `lift` is not connected here (its holder, if any, is elsewhere).
    fn elsewhere(&self, lift: &str) -> Option<&Arc<Cluster>> {
        self.registry
            .cluster()
            .filter(|_| !self.registry.connected_here(lift))
    }

    fn subscribers(&self, lift: &str) -> Arc<tokio::sync::Mutex<Subscribers>> {
        let mut lifts = self.lifts.lock().unwrap_or_else(PoisonError::into_inner);
        lifts.entry(lift.to_owned()).or_default().clone()
    }

    /// `subscriber` asks for `objects` of `lift` with `terms`. Kept when the gateway took the
    /// change (or it is offline and `offline` says keep); otherwise the gateway's failure.
    /// For a lift held by another process of the cluster, the request goes to its holder.
    pub async fn subscribe(
        &self,
        lift: &str,
        subscriber: &Subscriber,
        objects: &[Mplex],
        terms: Terms,
        offline: WhenOffline,
    ) -> Result<(), Failure> {
        let Some(cluster) = self.elsewhere(lift) else {
            return self
                .subscribe_local(lift, subscriber, objects, terms, offline)
                .await;
        };
        match cluster
            .request(lift, &subscribe_request(subscriber.clone(), objects, terms))
            .await
        {
            Ok(_) => {}
            Err(Failure::Gone) if offline == WhenOffline::Keep => {}
            Err(failure) => return Err(failure),
        }
        if self.own(subscriber) {
            // Kept here as well: handed to the lift's next holder.
            let cell = self.subscribers(lift);
            cell.lock()
                .await
                .add(&self.base, subscriber, objects, terms);
        }
        Ok(())
    }

    /// [`Subscriptions::hold`] asked by another process of the cluster of the lift held here.
    pub(crate) async fn subscribe_here(
        &self,
        lift: &str,
        subscriber: &Subscriber,
        objects: &[Mplex],
        terms: Terms,
    ) -> Result<(), Failure> {
        if !self.registry.connected_here(lift) {
            return Err(Failure::Gone);
        }
        self.subscribe_local(lift, subscriber, objects, terms, WhenOffline::Refuse)
            .await
    }

    async fn subscribe_local(
        &self,
        lift: &str,
        subscriber: &Subscriber,
        objects: &[Mplex],
        terms: Terms,
        offline: WhenOffline,
    ) -> Result<(), Failure> {
        let cell = self.subscribers(lift);
        let mut subscribers = cell.lock().await;
        let mut next = subscribers.clone();
        let changes = next.add(&self.base, subscriber, objects, terms);
        match self.send(lift, changes).await {
            Ok(()) => {}
            Err(Failure::Gone) if offline == WhenOffline::Keep => {}
            Err(failure) => {
                self.forget_if_empty(lift, &cell, &subscribers);
                return Err(failure);
            }
        }
        *subscribers = next;
        Ok(())
    }

    /// `subscriber` lets go of `objects` of `lift` (all of its own when `None`). The portal forgets
    /// them whatever the gateway answers (an offline gateway is told by the next connection's
    /// registrations); the gateway's failure is returned. For a lift held by another process
    /// of the cluster, its holder is told.
    pub async fn unsubscribe(
        &self,
        lift: &str,
        subscriber: &Subscriber,
        objects: Option<&[Mplex]>,
    ) -> Result<(), Failure> {
        let Some(cluster) = self.elsewhere(lift) else {
            return self.unsubscribe_local(lift, subscriber, objects).await;
        };
        {
            let cell = self.subscribers(lift);
            let mut subscribers = cell.lock().await;
            subscribers.remove(&self.base, subscriber, objects);
            self.forget_if_empty(lift, &cell, &subscribers);
        }
        let request = Relayed::Release(RelayedRelease {
            subscriber: subscriber.clone(),
            mplex: objects.map(|list| list.iter().map(|m| (*m).into()).collect()),
        });
        match cluster.request(lift, &request).await {
            Ok(_) | Err(Failure::Gone) => Ok(()),
            Err(failure) => Err(failure),
        }
    }

    /// [`Subscriptions::release`] asked by another process of the cluster of the lift held
    /// here.
    pub(crate) async fn unsubscribe_here(
        &self,
        lift: &str,
        subscriber: &Subscriber,
        objects: Option<&[Mplex]>,
    ) -> Result<(), Failure> {
        if !self.registry.connected_here(lift) {
            return Err(Failure::Gone);
        }
        self.unsubscribe_local(lift, subscriber, objects).await
    }

    async fn unsubscribe_local(
        &self,
        lift: &str,
        subscriber: &Subscriber,
        objects: Option<&[Mplex]>,
    ) -> Result<(), Failure> {
        let cell = self.subscribers(lift);
        let mut subscribers = cell.lock().await;
        let changes = subscribers.remove(&self.base, subscriber, objects);
        self.forget_if_empty(lift, &cell, &subscribers);
        match self.send(lift, changes).await {
            Err(Failure::Gone) => Ok(()),
            other => other,
        }
    }

    /// The watch lease of another process on `lift`, held here, lapsed (docs/CLUSTER.md
    /// §Subscriptions): that process died or lost NATS for longer than the lease, so its
    /// watchers let go of everything they hold (they ask again if they are still there).
    pub(crate) async fn unsubscribe_process(&self, lift: &str, process: u64) {
        if process == self.process {
            return;
        }
        let Some(cell) = self.existing(lift) else {
            return;
        };
        let mut subscribers = cell.lock().await;
        let changes = subscribers.remove_where(&self.base, |h| h.process() == Some(process));
        self.forget_if_empty(lift, &cell, &subscribers);
        if let Err(e) = self.send(lift, changes).await {
            tracing::debug!(%lift, failure = %e, "a lapsed process's subscriptions not unregistered");
        }
    }

    /// A gateway has just connected: register everything held on its lift — the users'
    /// subscriptions as the database has them, this process's watchers', and those other
    /// processes' watchers asked for since. A group the gateway refuses as a whole
    /// (`reg_canopen_object` is all or none, NXg §7.3: one object missing on this lift) is
    /// registered object by object.
    ///
    /// Users' subscriptions are read only when `stored` (the admission saw some): a reconnect
    /// storm of lifts nobody subscribed makes no query for them. Without, users' holds made
    /// since the connection was registered stay (the connection before left none).
    pub async fn resubscribe(&self, lift: &str, stored: bool) {
        let users = match stored {
            true => match self.store.subscribed_objects(lift).await {
                Ok(users) => Some(users),
                Err(e) => {
                    tracing::warn!(%lift, error = %e, "users' subscriptions not read: not registered");
                    Some(Vec::new())
                }
            },
            false => None,
        };
        let cell = self.subscribers(lift);
        let mut subscribers = cell.lock().await;
        if users.is_some() {
            subscribers.retain(|subscriber| !matches!(subscriber, Subscriber::User(_)));
        }
        for held in users.into_iter().flatten() {
            let Ok(mplex) = Mplex::parse(&held.mplex) else {
                tracing::warn!(%lift, mplex = %held.mplex, "a stored subscription that is no mplex");
                continue;
            };
            let terms = Terms {
                inhibit: held.inhibit,
                threshold: held.threshold,
            };
            subscribers.add(&self.base, &Subscriber::User(held.user), &[mplex], terms);
        }
        self.forget_if_empty(lift, &cell, &subscribers);
        for change in subscribers.all(&self.base) {
            let Change::Register(objects, terms) = change else {
                continue;
            };
            match self.register(lift, &objects, terms).await {
                Ok(()) => continue,
                Err(Failure::Error(_)) if objects.len() > 1 => {}
                Err(other) => {
                    tracing::debug!(%lift, failure = %other, "subscriptions not registered");
                    return;
                }
            }
            for mplex in objects {
                if let Err(e) = self.register(lift, &[mplex], terms).await {
                    tracing::debug!(%lift, %mplex, failure = %e, "object not subscribed");
                }
            }
        }
    }

    /// The lift's connection here ended: only this process's watchers stay (registered again
    /// on the next connection, or handed to the lift's next holder); users' come from the
    /// database again, other processes' watchers from their processes.
    pub async fn offline(&self, lift: &str) {
        self.asked
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .remove(lift);
        let Some(cell) = self.existing(lift) else {
            return;
        };
        let mut subscribers = cell.lock().await;
        subscribers.retain(|subscriber| self.own(subscriber));
        self.forget_if_empty(lift, &cell, &subscribers);
    }

    /// Another process of the cluster now holds `lift`, or its holder may have lost what this
    /// process's watchers asked for (NATS was away; the holder's answer to a watch says its
    /// lease was new): they ask the holder for their objects again (in the background; the
    /// same terms again change nothing at the gateway).
    pub(crate) fn moved(self: Arc<Self>, lift: &str) {
        let Some(cell) = self.existing(lift) else {
            return;
        };
        let lift = lift.to_owned();
        tokio::spawn(async move {
            let requests = {
                let mut subscribers = cell.lock().await;
                subscribers.retain(|subscriber| self.own(subscriber));
                self.forget_if_empty(&lift, &cell, &subscribers);
                subscribers.requests()
            };
            let Some(cluster) = self.registry.cluster() else {
                return;
            };
            for (subscriber, terms, objects) in requests {
                let request = subscribe_request(subscriber, &objects, terms);
                if let Err(e) = cluster.request(&lift, &request).await {
                    tracing::debug!(%lift, failure = %e, "a watcher's objects not handed to the lift's holder");
                }
            }
        });
    }

    fn existing(&self, lift: &str) -> Option<Arc<tokio::sync::Mutex<Subscribers>>> {
        let lifts = self.lifts.lock().unwrap_or_else(PoisonError::into_inner);
        lifts.get(lift).cloned()
    }

    /// A lift whose subscribers are all gone takes no memory (only one that anyone holds a
    /// subscription of beyond the dashboard's has an entry). Not while another call has the
    /// entry in hand: copies are taken only under the map's lock, so the map's and `cell`'s
    /// are the only ones when the count is two.
    fn forget_if_empty(
        &self,
        lift: &str,
        cell: &Arc<tokio::sync::Mutex<Subscribers>>,
        subscribers: &Subscribers,
    ) {
        if subscribers.is_empty() {
            let mut lifts = self.lifts.lock().unwrap_or_else(PoisonError::into_inner);
            if Arc::strong_count(cell) == 2 {
                lifts.remove(lift);
            }
        }
    }

    async fn send(&self, lift: &str, changes: Vec<Change>) -> Result<(), Failure> {
        for change in changes {
            match change {
                Change::Register(objects, terms) => self.register(lift, &objects, terms).await?,
                Change::Unregister(objects) => {
                    let params = UnregParams {
                        mplex: objects.iter().map(|m| (*m).into()).collect(),
                        node: None,
                    };
                    self.registry.call(lift, &params).await?;
                    let mut asked = self.asked.lock().unwrap_or_else(PoisonError::into_inner);
                    if let Some(set) = asked.get_mut(lift) {
                        for m in &objects {
                            set.remove(m);
                        }
                        if set.is_empty() {
                            asked.remove(lift);
                        }
                    }
                }
            }
        }
        Ok(())
    }

    async fn register(&self, lift: &str, objects: &[Mplex], terms: Terms) -> Result<(), Failure> {
        let extra: Vec<Mplex> = objects
            .iter()
            .filter(|m| !self.base.contains_key(m))
            .copied()
            .collect();
        if !extra.is_empty() {
            let mut asked = self.asked.lock().unwrap_or_else(PoisonError::into_inner);
            asked.entry(lift.to_owned()).or_default().extend(extra);
        }
        let params = RegParams {
            mplex: objects.iter().map(|m| (*m).into()).collect(),
            inhibit: terms.inhibit,
            threshold: terms.threshold,
            node: None,
        };
        self.registry.call(lift, &params).await.map(|_| ())
    }
}

/// `subscriber`'s request for `objects` with `terms`, to the lift's holder in the cluster.
fn subscribe_request(subscriber: Subscriber, objects: &[Mplex], terms: Terms) -> Relayed {
    Relayed::Hold(RelayedHold {
        subscriber,
        mplex: objects.iter().map(|m| (*m).into()).collect(),
        inhibit: terms.inhibit,
        threshold: terms.threshold,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn m(index: u16, sub: u8) -> Mplex {
        Mplex { index, sub }
    }

    fn terms(inhibit: u64, threshold: f64) -> Terms {
        Terms { inhibit, threshold }
    }

    fn dashboard() -> DashboardTerms {
        [(m(0x6520, 1), terms(500, 0.0))].into_iter().collect()
    }

    #[test]
    fn the_union_is_registered_and_released_holder_by_holder() {
        let base = dashboard();
        let mut h = Subscribers::default();
        let (a, w) = (Subscriber::User("masora".into()), Subscriber::Watcher(1));
        let trips = m(0x6520, 1);
        let speed = m(0x6383, 1);
        // A watcher wants the trip counter faster than the dashboard, and the speed (changes
        // come in the order of the objects).
        assert_eq!(
            h.add(&base, &w, &[trips, speed], terms(100, 0.5)),
            [
                Change::Register(vec![speed], terms(100, 0.5)),
                Change::Register(vec![trips], terms(100, 0.0)),
            ]
        );
        // An account asks for the speed more coarsely: nothing changes at the gateway.
        assert_eq!(h.add(&base, &a, &[speed], terms(1000, 2.0)), []);
        // The watcher ends: the trip counter goes back to the dashboard's terms, the speed to
        // the account's; nothing is unregistered.
        assert_eq!(
            h.remove(&base, &w, None),
            [
                Change::Register(vec![speed], terms(1000, 2.0)),
                Change::Register(vec![trips], terms(500, 0.0)),
            ]
        );
        // The account lets go of the trip counter it never held, then of the speed.
        assert_eq!(h.remove(&base, &a, Some(&[trips])), []);
        assert_eq!(
            h.remove(&base, &a, Some(&[speed])),
            [Change::Unregister(vec![speed])]
        );
        assert!(h.is_empty());
        // After a reconnect: the dashboard's objects.
        assert_eq!(
            h.all(&base),
            [Change::Register(vec![trips], terms(500, 0.0))]
        );
    }

    /// What stays when a lift's connection ends or moves, and what is handed to its next
    /// holder: one request per subscriber and terms.
    #[test]
    fn subscribers_are_kept_by_kind_and_asked_for_by_terms() {
        let base = dashboard();
        let mut h = Subscribers::default();
        let (user, mine, theirs) = (
            Subscriber::User("masora".into()),
            Subscriber::Watcher(1 << 32 | 1),
            Subscriber::Watcher(2 << 32 | 1),
        );
        let (trips, speed, door) = (m(0x6520, 1), m(0x6383, 1), m(0x6300, 1));
        h.add(&base, &user, &[trips], terms(1000, 0.0));
        h.add(&base, &mine, &[speed, door], terms(100, 0.5));
        h.add(&base, &mine, &[trips], terms(0, 0.0));
        h.add(&base, &theirs, &[speed], terms(10, 0.0));
        h.retain(|subscriber| subscriber == &mine);
        assert_eq!(
            h.requests(),
            [
                (mine.clone(), terms(100, 0.5), vec![door, speed]),
                (mine.clone(), terms(0, 0.0), vec![trips]),
            ]
        );
        h.retain(|_| false);
        assert!(h.is_empty());
        assert_eq!(h.requests(), []);
    }

    /// A process whose watch lapsed: all its watchers let go at once, each object falling
    /// back to what the others hold (the user, the dashboard) or leaving the gateway.
    #[test]
    fn a_process_lets_go_of_all_its_watchers_at_once() {
        let base = dashboard();
        let mut h = Subscribers::default();
        let user = Subscriber::User("masora".into());
        let (first, second, other) = (
            Subscriber::Watcher(2 << 32 | 1),
            Subscriber::Watcher(2 << 32 | 2),
            Subscriber::Watcher(3 << 32 | 1),
        );
        assert_eq!(first.process(), Some(2 << 32));
        assert_eq!(user.process(), None);
        let (trips, speed, door, load) = (m(0x6520, 1), m(0x6383, 1), m(0x6300, 1), m(0x6600, 1));
        h.add(&base, &user, &[speed], terms(1000, 0.0));
        h.add(&base, &first, &[trips, speed], terms(100, 0.0));
        h.add(&base, &second, &[door], terms(0, 0.0));
        h.add(&base, &other, &[load], terms(50, 0.0));
        let changes = h.remove_where(&base, |subscriber| subscriber.process() == Some(2 << 32));
        assert_eq!(
            changes,
            [
                Change::Register(vec![speed], terms(1000, 0.0)),
                Change::Register(vec![trips], terms(500, 0.0)),
                Change::Unregister(vec![door]),
            ]
        );
        assert_eq!(
            h.requests(),
            [
                (user.clone(), terms(1000, 0.0), vec![speed]),
                (other.clone(), terms(50, 0.0), vec![load]),
            ]
        );
    }

    proptest! {
        /// Whatever subscribers add and remove, replaying the changes on a model of the gateway
        /// leaves it with exactly the union of what is held, as a reconnect would register it.
        #[test]
        fn the_gateway_always_has_the_union(
            steps in proptest::collection::vec(
                (0u64..3, proptest::collection::vec(0u8..4, 0..4), 0u64..3, 0u8..3, any::<bool>()),
                0..40,
            )
        ) {
            let base = dashboard();
            let mut h = Subscribers::default();
            let mut gateway: BTreeMap<Mplex, Terms> = BTreeMap::new();
            let apply = |gateway: &mut BTreeMap<Mplex, Terms>, changes: Vec<Change>| {
                for change in changes {
                    match change {
                        Change::Register(list, t) => {
                            for mplex in list {
                                gateway.insert(mplex, t);
                            }
                        }
                        Change::Unregister(list) => {
                            for mplex in list {
                                gateway.remove(&mplex);
                            }
                        }
                    }
                }
            };
            apply(&mut gateway, h.all(&base));
            for (who, subs, inhibit, threshold, add) in steps {
                let subscriber = Subscriber::Watcher(who);
                let objects: Vec<Mplex> = subs.iter().map(|s| m(0x6520, *s)).collect();
                let changes = if add {
                    h.add(&base, &subscriber, &objects, terms(inhibit * 100, f64::from(threshold)))
                } else {
                    h.remove(&base, &subscriber, (!objects.is_empty()).then_some(&objects[..]))
                };
                apply(&mut gateway, changes);
                let mut fresh = BTreeMap::new();
                apply(&mut fresh, h.all(&base));
                prop_assert_eq!(&gateway, &fresh);
            }
        }
    }
}
