//! New connections closed at once while gateways wait too long for CONNACK (docs/PORTAL.md
//! §Overload).
//!
//! A gateway gives up a connection that has no CONNACK within its connect timeout (10 s by
//! default, docs/GATEWAY.md) and connects again after its backoff. A portal offered more
//! connections than it can admit in that time works for connections whose gateways have gone
//! already, and the queue ahead of the next ones stays as long: the fleet comes online the
//! slower, the harder it tries (docs/BENCHMARKS.md §NATS on one thread: 50,904 CONNECTs
//! admitted for 30,000 gateways). So while the last CONNACKs came later than `[gateways]
//! shed_after_ms` after their connection was accepted, and many connections are on their way,
//! a new TCP connection is closed before its TLS handshake — the cheapest refusal there is. Its
//! gateway backs off; those in the queue get their CONNACK in time.

use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Connections on their way (in their TLS handshake, or upgraded and not yet admitted) below
/// which none is closed, whatever the last CONNACKs took: the queue is short, and a few
/// connections that hold it without sending CONNECT cannot make the portal refuse others.
const MIN_ON_THE_WAY: usize = 64;

/// How recent the last CONNACK must be to count: a portal no longer admitting anything is not
/// busy admitting.
const FRESH: Duration = Duration::from_secs(1);

/// The portal's measure of how long connections wait for CONNACK, and its decision to shed.
#[derive(Debug)]
pub struct Overload {
    after: Option<Duration>,
    since: Instant,
    on_the_way: AtomicUsize,
    /// How long the last CONNACK came after its connection's accept (ms).
    last_wait_ms: AtomicU64,
    /// When it came (ms after `since`).
    last_at_ms: AtomicU64,
    shed: AtomicU64,
}

/// A connection on its way to CONNACK: counted until dropped.
#[derive(Debug)]
pub struct OnTheWay(Arc<Overload>);

impl Drop for OnTheWay {
    fn drop(&mut self) {
        self.0.on_the_way.fetch_sub(1, Ordering::Relaxed);
    }
}

/// When a connection was accepted, and its place among those on their way; handed from the
/// accept to the gateway connection, which reports its CONNACK ([`Arrival::connacked`]).
#[derive(Debug)]
pub struct Arrival {
    accepted: Instant,
    _on_the_way: OnTheWay,
}

impl Arrival {
    /// The gateway is admitted: how long it waited counts for the next decisions, and it is no
    /// longer on its way.
    pub fn connacked(self, now: Instant) {
        let overload = &self._on_the_way.0;
        overload.report(now.saturating_duration_since(self.accepted), now);
    }
}

impl Overload {
    /// Shedding after `after` of waiting for CONNACK; `None`: never.
    pub fn new(after: Option<Duration>) -> Arc<Overload> {
        Arc::new(Overload {
            after,
            since: Instant::now(),
            on_the_way: AtomicUsize::new(0),
            last_wait_ms: AtomicU64::new(0),
            last_at_ms: AtomicU64::new(0),
            shed: AtomicU64::new(0),
        })
    }

    /// A TCP connection accepted at `now`: `Some` to serve it (on its way until the guard is
    /// dropped: after the TLS handshake, see [`Overload::arrival`]), `None` to close it at once
    /// (counted).
    pub fn accept(self: &Arc<Self>, now: Instant) -> Option<OnTheWay> {
        if self.overloaded(now) {
            self.shed.fetch_add(1, Ordering::Relaxed);
            return None;
        }
        Some(self.on_the_way())
    }

    /// A gateway's WebSocket upgrade of a connection accepted at `accepted`: on its way until
    /// its CONNACK or its end.
    pub fn arrival(self: &Arc<Self>, accepted: Instant) -> Arrival {
        Arrival {
            accepted,
            _on_the_way: self.on_the_way(),
        }
    }

    /// Connections closed at once so far (`canlift_connections_shed_total`).
    pub fn shed_total(&self) -> u64 {
        self.shed.load(Ordering::Relaxed)
    }

    fn on_the_way(self: &Arc<Self>) -> OnTheWay {
        self.on_the_way.fetch_add(1, Ordering::Relaxed);
        OnTheWay(self.clone())
    }

    fn report(&self, waited: Duration, now: Instant) {
        let ms = |d: Duration| u64::try_from(d.as_millis()).unwrap_or(u64::MAX);
        self.last_wait_ms.store(ms(waited), Ordering::Relaxed);
        self.last_at_ms.store(
            ms(now.saturating_duration_since(self.since)),
            Ordering::Relaxed,
        );
    }

    fn overloaded(&self, now: Instant) -> bool {
        let Some(after) = self.after else {
            return false;
        };
        if self.on_the_way.load(Ordering::Relaxed) < MIN_ON_THE_WAY {
            return false;
        }
        let last_at = self.since + Duration::from_millis(self.last_at_ms.load(Ordering::Relaxed));
        now.saturating_duration_since(last_at) <= FRESH
            && Duration::from_millis(self.last_wait_ms.load(Ordering::Relaxed)) > after
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` connections accepted at `at` and upgraded, on their way.
    fn arrivals(overload: &Arc<Overload>, n: usize, at: Instant) -> Vec<Arrival> {
        (0..n).map(|_| overload.arrival(at)).collect()
    }

    #[test]
    fn connections_are_shed_only_while_many_wait_and_the_last_connack_came_late() {
        let overload = Overload::new(Some(Duration::from_secs(5)));
        let t0 = Instant::now();
        let mut waiting = arrivals(&overload, MIN_ON_THE_WAY + 10, t0);
        // No CONNACK yet: nothing to go by.
        assert!(overload.accept(t0).is_some());
        // A CONNACK 4 s after its accept: in time.
        waiting
            .pop()
            .unwrap()
            .connacked(t0 + Duration::from_secs(4));
        assert!(overload.accept(t0 + Duration::from_secs(4)).is_some());
        // 6 s: late, with many still on their way.
        let late = t0 + Duration::from_secs(6);
        waiting.pop().unwrap().connacked(late);
        assert!(overload.accept(late).is_none());
        assert!(overload.accept(late + Duration::from_millis(900)).is_none());
        assert_eq!(overload.shed_total(), 2);
        // Nothing admitted for more than a second: not busy admitting, whatever it took.
        assert!(overload.accept(late + Duration::from_secs(2)).is_some());
        // Late again, but the queue has drained below the floor: taken.
        waiting.pop().unwrap().connacked(late);
        waiting.truncate(MIN_ON_THE_WAY - 2);
        assert!(overload.accept(late).is_some());
        // Many on their way again and late: shed; a CONNACK in time ends it.
        let mut more = arrivals(&overload, 10, late);
        overload.arrival(t0).connacked(late);
        assert!(overload.accept(late).is_none());
        let fast = late + Duration::from_millis(100);
        more.pop().unwrap().connacked(fast);
        assert!(overload.accept(fast).is_some());
        assert_eq!(overload.shed_total(), 3);
    }

    #[test]
    fn guards_count_the_connections_on_their_way() {
        let overload = Overload::new(Some(Duration::from_millis(1)));
        let now = Instant::now();
        let tcp = overload.accept(now).unwrap();
        let upgraded = overload.arrival(now);
        assert_eq!(overload.on_the_way.load(Ordering::Relaxed), 2);
        drop(tcp);
        upgraded.connacked(now);
        assert_eq!(overload.on_the_way.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn without_a_limit_nothing_is_shed() {
        let overload = Overload::new(None);
        let t0 = Instant::now();
        let mut waiting = arrivals(&overload, 2 * MIN_ON_THE_WAY, t0);
        let late = t0 + Duration::from_secs(60);
        waiting.pop().unwrap().connacked(late);
        assert!(overload.accept(late).is_some());
        assert_eq!(overload.shed_total(), 0);
    }
}
