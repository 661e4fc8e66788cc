//! Live events across the cluster: a lift's holder publishes its events on the lift's events
//! subject while another process watches it (for a lease, renewed by the watcher), and a
//! watching process forwards them to its viewers.

use std::collections::HashMap;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use futures_util::StreamExt;
use tokio::sync::{broadcast, mpsc, oneshot};

use cloud_types::live::LiftEvent;

use crate::msgs::{self, Relayed, RelayedWatch};
use crate::{lock, Cluster, NEW_LEASE, WATCH_ASK};

impl Cluster {
    /// Hand a held lift's live event to the other processes that watch it (dropped and
    /// counted when NATS lags far behind); an event nobody elsewhere watches is not published.
    pub fn publish(&self, lift: &str, event: &LiftEvent) {
        if !self.watched_elsewhere(lift) {
            self.counters
                .events_unwatched
                .fetch_add(1, Ordering::Relaxed);
            return;
        }
        let Ok(body) = serde_json::to_vec(event) else {
            return;
        };
        if self.events.try_send((lift.to_owned(), body)).is_err() {
            self.counters.events_dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Whether another process's watch of `lift` holds.
    pub(crate) fn watched_elsewhere(&self, lift: &str) -> bool {
        lock(&self.watched).any(lift, Instant::now())
    }

    /// Another process watches `lift`, held here: publish its live events, and keep its
    /// watchers' subscriptions, for a lease. Whether its lease was still running (else this
    /// one is new).
    pub(crate) fn watch_granted(&self, lift: &str, process: u64) -> bool {
        lock(&self.watched).grant(lift, process, Instant::now(), self.lease())
    }

    /// The processes whose watch of the held `lift` lapsed let go of their watchers'
    /// subscriptions (in the background): they died, or lost NATS for longer than the lease.
    pub(crate) fn release_lapsed(&self, lift: String, lapsed: Vec<u64>) {
        self.counters
            .watch_lapsed
            .fetch_add(lapsed.len() as u64, Ordering::Relaxed);
        let Some(local) = self.local() else {
            return;
        };
        tokio::spawn(async move {
            for process in lapsed {
                tracing::debug!(%lift, process = process >> 32, "a watching process's lease lapsed");
                local.unsubscribe_process(&lift, process).await;
            }
        });
    }

    /// Ask the holder of `lift` to publish its live events (for a lease), waiting at most
    /// [`WATCH_ASK`]; no holder or no NATS is no matter (then there is nothing to publish).
    /// A lift that moved here needs no asking: its events reach the watchers here directly.
    pub(crate) async fn ask_to_publish(self: Arc<Self>, lift: String) {
        if lock(&self.held).contains_key(&lift) {
            return;
        }
        let Some(local) = self.local() else {
            return;
        };
        let watch = Relayed::Watch(RelayedWatch {
            process: local.process(),
        });
        match tokio::time::timeout(WATCH_ASK, self.relay(&lift, &watch)).await {
            // The holder has none of this process's watchers' subscriptions: hand them over.
            Ok(Ok(answer)) if answer == NEW_LEASE => local.moved(&lift),
            Ok(Err(e)) => tracing::debug!(%lift, error = ?e, "NATS: watch not taken"),
            _ => {}
        }
    }

    /// Publish the live events the registry queued for other processes, in order.
    pub async fn publish_events(self: Arc<Self>, mut queue: mpsc::Receiver<(String, Vec<u8>)>) {
        while let Some((lift, body)) = queue.recv().await {
            if !self.connected() {
                continue;
            }
            let mut headers = async_nats::HeaderMap::new();
            headers.insert(msgs::ORIGIN, self.node.as_str());
            let subject = msgs::events_subject(&lift);
            if let Err(e) = self
                .client
                .publish_with_headers(subject, headers, body.into())
                .await
            {
                tracing::debug!(%lift, error = %e, "NATS: event not published");
            }
        }
    }

    /// Someone on this process watches `lift` (`tx` is its channel): pass on the events other
    /// processes publish for it, until nobody here watches. The receiver (`None`: already
    /// forwarding) tells when the NATS server has the subscription.
    pub fn forward(
        self: &Arc<Self>,
        lift: &str,
        tx: &broadcast::Sender<LiftEvent>,
    ) -> Option<oneshot::Receiver<()>> {
        {
            let mut forwarded = lock(&self.forwarded);
            if forwarded.get(lift).is_some_and(|f| f.same_channel(tx)) {
                return None;
            }
            forwarded.insert(lift.to_owned(), tx.clone());
        }
        let (ready, subscribed) = oneshot::channel();
        tokio::spawn(self.clone().forwarder(lift.to_owned(), tx.clone(), ready));
        Some(subscribed)
    }

    async fn forwarder(
        self: Arc<Self>,
        lift: String,
        tx: broadcast::Sender<LiftEvent>,
        ready: oneshot::Sender<()>,
    ) {
        if let Ok(mut events) = self.client.subscribe(msgs::events_subject(&lift)).await {
            if self.client.flush().await.is_ok() {
                // The holder publishes only what someone watches: ask before saying ready.
                self.clone().ask_to_publish(lift.clone()).await;
                let _ = ready.send(());
            }
            let mut generation = self.generation.subscribe();
            let renewal = self.renewal();
            let mut check =
                tokio::time::interval_at(tokio::time::Instant::now() + renewal, renewal);
            loop {
                tokio::select! {
                    message = events.next() => {
                        let Some(message) = message else { break };
                        let origin = message.headers.as_ref().and_then(|h| h.get(msgs::ORIGIN));
                        if origin.is_some_and(|o| o.as_str() == self.node) {
                            continue;
                        }
                        let Ok(event) = serde_json::from_slice::<LiftEvent>(&message.payload) else {
                            continue;
                        };
                        if tx.send(event).is_err() {
                            break;
                        }
                    }
                    _ = check.tick() => {
                        if tx.receiver_count() == 0 {
                            break;
                        }
                        tokio::spawn(self.clone().ask_to_publish(lift.clone()));
                    }
                    // NATS is back (perhaps restarted): the holder's lease may have lapsed, and
                    // with it the watchers' subscriptions there; holds relayed meanwhile failed.
                    Ok(()) = generation.changed() => {
                        if !lock(&self.held).contains_key(&lift) {
                            if let Some(local) = self.local() {
                                local.moved(&lift);
                            }
                        }
                        tokio::spawn(self.clone().ask_to_publish(lift.clone()));
                    }
                }
            }
            let _ = events.unsubscribe().await;
        }
        let mut forwarded = lock(&self.forwarded);
        if forwarded.get(&lift).is_some_and(|f| f.same_channel(&tx)) {
            forwarded.remove(&lift);
        }
    }
}

/// Which other processes watch which lifts held here, and until when: per lift, per watching
/// process (its part of its watchers' ids). Only watched lifts have an entry.
#[derive(Debug, Default)]
pub(crate) struct Leases(HashMap<String, HashMap<u64, Instant>>);

impl Leases {
    /// `process` watches `lift` from `now` for `lease`; whether its lease was still running
    /// (else this one is new).
    pub(crate) fn grant(
        &mut self,
        lift: &str,
        process: u64,
        now: Instant,
        lease: Duration,
    ) -> bool {
        self.0
            .entry(lift.to_owned())
            .or_default()
            .insert(process, now + lease)
            .is_some_and(|until| until > now)
    }

    /// Whether any process's lease of `lift` runs at `now`.
    pub(crate) fn any(&self, lift: &str, now: Instant) -> bool {
        self.0
            .get(lift)
            .is_some_and(|leases| leases.values().any(|until| *until > now))
    }

    /// Per lift, the processes whose lease ran out by `now`, forgotten.
    pub(crate) fn lapsed_all(&mut self, now: Instant) -> Vec<(String, Vec<u64>)> {
        let mut lapsed_all = Vec::new();
        self.0.retain(|lift, leases| {
            let mut lapsed = Vec::new();
            leases.retain(|process, until| {
                let running = *until > now;
                if !running {
                    lapsed.push(*process);
                }
                running
            });
            if !lapsed.is_empty() {
                lapsed_all.push((lift.clone(), lapsed));
            }
            !leases.is_empty()
        });
        lapsed_all
    }

    /// `lift` is no longer held here: its leases go with it.
    pub(crate) fn forget(&mut self, lift: &str) {
        self.0.remove(lift);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const LEASE: Duration = Duration::from_secs(30);

    /// The processes whose lease of lift `L` lapsed by `now`.
    fn lapsed(leases: &mut Leases, now: Instant) -> Vec<u64> {
        let mut all = leases.lapsed_all(now);
        assert!(all.iter().all(|(lift, _)| lift == "L"));
        all.pop()
            .map(|(_, processes)| processes)
            .unwrap_or_default()
    }

    #[test]
    fn a_lease_runs_until_it_lapses_per_process() {
        let t0 = Instant::now();
        let second = |n: u64| t0 + Duration::from_secs(n);
        let (a, b) = (1 << 32, 2 << 32);
        let mut leases = Leases::default();
        assert!(!leases.any("L", t0));
        assert!(!leases.grant("L", a, t0, LEASE), "a first lease is new");
        assert!(leases.grant("L", a, second(10), LEASE), "renewed in time");
        assert!(!leases.grant("L", b, second(20), LEASE));
        assert!(leases.any("L", second(39)));
        assert!(lapsed(&mut leases, second(39)).is_empty());
        // a's lease (renewed at 10 s) ends at 40 s, b's at 50 s.
        assert_eq!(lapsed(&mut leases, second(40)), vec![a]);
        assert!(leases.any("L", second(45)));
        assert!(
            !leases.grant("L", a, second(45), LEASE),
            "lapsed: new again"
        );
        assert_eq!(lapsed(&mut leases, second(50)), vec![b]);
        assert_eq!(lapsed(&mut leases, second(80)), vec![a]);
        assert!(leases.0.is_empty(), "an unwatched lift takes no entry");
        assert!(!leases.any("L", second(80)));
    }

    #[test]
    fn a_lease_not_swept_in_time_is_new_when_asked_again() {
        let t0 = Instant::now();
        let mut leases = Leases::default();
        leases.grant("L", 1 << 32, t0, LEASE);
        assert!(!leases.grant("L", 1 << 32, t0 + LEASE, LEASE));
        leases.forget("L");
        assert!(!leases.any("L", t0));
        assert!(lapsed(&mut leases, t0 + LEASE * 3).is_empty());
    }
}
