//! Throttling (docs/PORTAL.md §Throttling), sans-IO: every decision takes the time as input.
//!
//! - [`TokenBucket`]: a rate with bursts, for the messages of one gateway and the requests of
//!   one API key.
//! - [`SignIns`]: failed sign-ins per user name and per source address; after a few, each
//!   further failure makes the next attempt wait twice as long as the one before (1 s … 15 min),
//!   so guessing a secret costs time and the logs stay quiet, while a person who mistyped waits
//!   at most seconds.

use std::collections::HashMap;
use std::time::{Duration, Instant};

/// A rate of `per_s` on average with bursts of up to `capacity` (by default two seconds' worth).
#[derive(Debug, Clone)]
pub struct TokenBucket {
    per_s: f64,
    capacity: f64,
    tokens: f64,
    at: Instant,
}

impl TokenBucket {
    /// A full bucket at `now`: `per_s` events a second, bursts of two seconds' worth.
    pub fn new(per_s: u32, now: Instant) -> TokenBucket {
        let per_s = f64::from(per_s.max(1));
        TokenBucket::with_capacity(per_s, 2.0 * per_s, now)
    }

    /// A full bucket at `now` of `per_s` units a second (at least a millionth) and bursts of
    /// `capacity` units.
    pub fn with_capacity(per_s: f64, capacity: f64, now: Instant) -> TokenBucket {
        let per_s = per_s.max(1e-6);
        TokenBucket {
            per_s,
            capacity,
            tokens: capacity,
            at: now,
        }
    }

    /// One event at `now`: `Ok` within the rate, otherwise how long until one would be.
    pub fn take(&mut self, now: Instant) -> Result<(), Duration> {
        self.take_n(1.0, now)
    }

    /// `n` units at `now`: `Ok` (and taken) within the rate, otherwise how long until they
    /// would be (nothing taken).
    pub fn take_n(&mut self, n: f64, now: Instant) -> Result<(), Duration> {
        self.tokens = (self.tokens + self.refill(now)).min(self.capacity());
        self.at = now;
        if self.tokens < n {
            return Err(Duration::from_secs_f64((n - self.tokens) / self.per_s));
        }
        self.tokens -= n;
        Ok(())
    }

    /// Undo one [`Self::take`] that turned out not to count (never above a full bucket).
    pub fn give_back(&mut self) {
        self.tokens = (self.tokens + 1.0).min(self.capacity());
    }

    /// Whether it has been full since `now` (an idle key's bucket can be forgotten).
    fn full(&self, now: Instant) -> bool {
        self.tokens + self.refill(now) >= self.capacity()
    }

    /// What has flowed in since the last [`Self::take`].
    fn refill(&self, now: Instant) -> f64 {
        now.saturating_duration_since(self.at).as_secs_f64() * self.per_s
    }

    fn capacity(&self) -> f64 {
        self.capacity
    }
}

/// The key a source address is limited by: itself for IPv4, its /64 for IPv6 (one host is
/// given a whole /64 to choose addresses from).
pub fn address_key(peer: &str) -> String {
    let ip = peer
        .parse::<std::net::SocketAddr>()
        .map(|a| a.ip())
        .or_else(|_| peer.parse::<std::net::IpAddr>());
    match ip {
        Ok(std::net::IpAddr::V6(v6)) => match v6.to_ipv4_mapped() {
            Some(v4) => v4.to_string(),
            None => {
                let s = v6.segments();
                format!("{:x}:{:x}:{:x}:{:x}::/64", s[0], s[1], s[2], s[3])
            }
        },
        Ok(ip) => ip.to_string(),
        Err(_) => peer.to_owned(),
    }
}

/// Events per source address ([`address_key`]), each address its own bucket of `per_s` with
/// bursts of `burst`. At most [`LIMIT`] addresses are followed; when full, the idle ones
/// (full again) are forgotten first, then all.
#[derive(Debug)]
pub struct AddressRates {
    per_s: f64,
    burst: f64,
    buckets: HashMap<String, TokenBucket>,
}

impl AddressRates {
    /// `per_s` events a second per address, bursts of `burst`.
    pub fn new(per_s: f64, burst: f64) -> AddressRates {
        AddressRates {
            per_s,
            burst,
            buckets: HashMap::new(),
        }
    }

    /// One event from `peer` at `now`: whether it is within its address's rate.
    pub fn take(&mut self, peer: &str, now: Instant) -> bool {
        if self.buckets.len() >= LIMIT {
            self.buckets.retain(|_, b| !b.full(now));
            if self.buckets.len() >= LIMIT {
                self.buckets.clear();
            }
        }
        let (per_s, burst) = (self.per_s, self.burst);
        self.buckets
            .entry(address_key(peer))
            .or_insert_with(|| TokenBucket::with_capacity(per_s, burst, now))
            .take(now)
            .is_ok()
    }
}

/// Requests per API key (by its digest), each key its own bucket. At most `LIMIT` keys are
/// followed; when full, idle keys' buckets (full again) are forgotten first, then all.
#[derive(Debug)]
pub struct KeyRates {
    per_s: u32,
    buckets: HashMap<String, TokenBucket>,
}

const LIMIT: usize = 100_000;

impl KeyRates {
    /// `per_s` requests per second and key (0: no limit).
    pub fn new(per_s: u32) -> KeyRates {
        KeyRates {
            per_s,
            buckets: HashMap::new(),
        }
    }

    /// A request with key `digest` at `now`: `Err(wait)` when over the key's rate.
    pub fn take(&mut self, digest: &str, now: Instant) -> Result<(), Duration> {
        if self.per_s == 0 {
            return Ok(());
        }
        if self.buckets.len() >= LIMIT && !self.buckets.contains_key(digest) {
            self.buckets.retain(|_, b| !b.full(now));
            if self.buckets.len() >= LIMIT {
                self.buckets.clear();
            }
        }
        let per_s = self.per_s;
        self.buckets
            .entry(digest.to_owned())
            .or_insert_with(|| TokenBucket::new(per_s, now))
            .take(now)
    }
}

/// Failures allowed before attempts have to wait.
const FREE_FAILURES: u32 = 5;
/// The longest wait.
const MAX_WAIT: Duration = Duration::from_secs(15 * 60);
/// Failures older than this are forgotten.
const FORGET_AFTER: Duration = Duration::from_secs(3600);

#[derive(Debug, Clone, Copy)]
struct Failures {
    count: u32,
    last: Instant,
}

impl Failures {
    /// When the next attempt may be made.
    fn next_at(&self) -> Instant {
        let over = self.count.saturating_sub(FREE_FAILURES);
        if over == 0 {
            return self.last;
        }
        let wait = Duration::from_secs(1u64 << (over - 1).min(20)).min(MAX_WAIT);
        self.last + wait
    }
}

/// Failed sign-ins by user name and by source address.
#[derive(Debug, Default)]
pub struct SignIns {
    failures: HashMap<String, Failures>,
}

impl SignIns {
    fn keys(user: &str, address: &str) -> [String; 2] {
        [format!("user {user}"), format!("address {address}")]
    }

    /// Whether `user` may try from `address` at `now`: `Err(wait)` while either has to wait.
    pub fn check(&self, user: &str, address: &str, now: Instant) -> Result<(), Duration> {
        let wait = Self::keys(user, address)
            .iter()
            .filter_map(|k| self.failures.get(k))
            .map(|f| f.next_at().saturating_duration_since(now))
            .max()
            .unwrap_or_default();
        if wait.is_zero() {
            Ok(())
        } else {
            Err(wait)
        }
    }

    /// `user` failed from `address` at `now`.
    pub fn failed(&mut self, user: &str, address: &str, now: Instant) {
        if self.failures.len() >= LIMIT {
            self.failures
                .retain(|_, f| now.saturating_duration_since(f.last) < FORGET_AFTER);
            if self.failures.len() >= LIMIT {
                self.failures.clear();
            }
        }
        for key in Self::keys(user, address) {
            let entry = self.failures.entry(key).or_insert(Failures {
                count: 0,
                last: now,
            });
            if now.saturating_duration_since(entry.last) >= FORGET_AFTER {
                entry.count = 0;
            }
            entry.count += 1;
            entry.last = now;
        }
    }

    /// `user` signed in from `address`: both start over.
    pub fn succeeded(&mut self, user: &str, address: &str) {
        for key in Self::keys(user, address) {
            self.failures.remove(&key);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bucket_allows_a_burst_of_two_seconds_then_the_average() {
        let start = Instant::now();
        let mut rate = TokenBucket::new(100, start);
        assert!(
            (0..200).all(|_| rate.take(start).is_ok()),
            "two seconds' worth at once"
        );
        let wait = rate.take(start).expect_err("then nothing more");
        assert!(
            wait <= Duration::from_millis(10) && !wait.is_zero(),
            "{wait:?}"
        );
        // 100 per second refill: 10 ms brings one.
        assert!(rate.take(start + Duration::from_millis(10)).is_ok());
        assert!(rate.take(start + Duration::from_millis(10)).is_err());
        // A steady 100/s is always within the rate.
        let steady = (1..=1000).all(|i| {
            rate.take(start + Duration::from_millis(10 + 10 * i))
                .is_ok()
        });
        assert!(steady);
        // 200/s is not for long.
        let later = start + Duration::from_secs(20);
        let mut fast = TokenBucket::new(100, later);
        let accepted = (0..2000)
            .take_while(|i| fast.take(later + Duration::from_millis(5 * i)).is_ok())
            .count();
        assert!((390..=410).contains(&accepted), "{accepted}");
        assert!(fast.full(later + Duration::from_secs(30)));
    }

    #[test]
    fn what_is_given_back_can_be_taken_again_but_never_beyond_a_full_bucket() {
        let start = Instant::now();
        let mut rate = TokenBucket::new(10, start);
        assert!((0..20).all(|_| rate.take(start).is_ok()));
        assert!(rate.take(start).is_err());
        rate.give_back();
        assert!(rate.take(start).is_ok(), "the one given back");
        assert!(rate.take(start).is_err());
        // Given back into a full bucket: still two seconds' worth, not one more.
        let mut full = TokenBucket::new(10, start);
        full.give_back();
        assert_eq!((0..30).take_while(|_| full.take(start).is_ok()).count(), 20);
    }

    #[test]
    fn a_bucket_of_units_takes_what_fits() {
        let t0 = Instant::now();
        // 3,600 units an hour, bursts of an hour's worth.
        let mut b = TokenBucket::with_capacity(1.0, 3600.0, t0);
        assert!(b.take_n(3000.0, t0).is_ok());
        assert_eq!(b.take_n(1000.0, t0), Err(Duration::from_secs(400)));
        assert!(
            b.take_n(600.0, t0).is_ok(),
            "what did not fit was not taken"
        );
        assert!(b.take_n(10.0, t0 + Duration::from_secs(10)).is_ok());
    }

    #[test]
    fn addresses_are_limited_alone_and_ipv6_by_its_64() {
        assert_eq!(address_key("192.0.2.7:4711"), "192.0.2.7");
        assert_eq!(
            address_key("[2001:db8:1:2:aaaa::1]:443"),
            "2001:db8:1:2::/64"
        );
        assert_eq!(address_key("[::ffff:192.0.2.7]:1"), "192.0.2.7");
        let t0 = Instant::now();
        let mut rates = AddressRates::new(1.0, 2.0);
        assert!(rates.take("192.0.2.7:1", t0) && rates.take("192.0.2.7:2", t0));
        assert!(!rates.take("192.0.2.7:3", t0), "a third at once is over");
        assert!(rates.take("192.0.2.8:1", t0), "another address has its own");
        assert!(rates.take("[2001:db8:1:2::1]:1", t0) && rates.take("[2001:db8:1:2::2]:1", t0));
        assert!(
            !rates.take("[2001:db8:1:2:ffff::9]:1", t0),
            "the same /64 shares one bucket"
        );
        assert!(rates.take("192.0.2.7:4", t0 + Duration::from_secs(1)));
    }

    #[test]
    fn keys_have_their_own_buckets() {
        let t0 = Instant::now();
        let mut rates = KeyRates::new(1);
        assert!(rates.take("a", t0).is_ok() && rates.take("a", t0).is_ok());
        assert!(rates.take("a", t0).is_err());
        assert!(rates.take("b", t0).is_ok());
        let mut unlimited = KeyRates::new(0);
        assert!((0..1000).all(|_| unlimited.take("a", t0).is_ok()));
    }

    #[test]
    fn failed_sign_ins_make_the_next_wait_longer() {
        let t0 = Instant::now();
        let mut s = SignIns::default();
        for _ in 0..FREE_FAILURES {
            assert_eq!(s.check("ann", "10.0.0.1", t0), Ok(()));
            s.failed("ann", "10.0.0.1", t0);
        }
        assert_eq!(s.check("ann", "10.0.0.1", t0), Ok(()));
        s.failed("ann", "10.0.0.1", t0);
        // The sixth failure: 1 s for the name from anywhere, and for anyone from the address.
        assert_eq!(s.check("ann", "10.0.0.2", t0), Err(Duration::from_secs(1)));
        assert_eq!(s.check("bob", "10.0.0.1", t0), Err(Duration::from_secs(1)));
        assert_eq!(s.check("bob", "10.0.0.2", t0), Ok(()));
        let t1 = t0 + Duration::from_secs(1);
        assert_eq!(s.check("ann", "10.0.0.1", t1), Ok(()));
        s.failed("ann", "10.0.0.1", t1);
        assert_eq!(s.check("ann", "10.0.0.1", t1), Err(Duration::from_secs(2)));
        // Many more: at most 15 minutes.
        for _ in 0..40 {
            s.failed("ann", "10.0.0.1", t1);
        }
        assert_eq!(s.check("ann", "10.0.0.1", t1), Err(MAX_WAIT));
        // A success clears both; an hour without failures forgets them.
        s.succeeded("ann", "10.0.0.1");
        assert_eq!(s.check("ann", "10.0.0.1", t1), Ok(()));
        for _ in 0..=FREE_FAILURES {
            s.failed("bob", "10.0.0.3", t1);
        }
        let later = t1 + FORGET_AFTER;
        s.failed("bob", "10.0.0.3", later);
        assert_eq!(
            s.check("bob", "10.0.0.3", later),
            Ok(()),
            "counted from one again"
        );
    }
}
