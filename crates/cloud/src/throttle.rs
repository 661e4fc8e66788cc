//! Throttling (docs/PORTAL.md §Users and roles), sans-IO: every decision takes the time as input.
//!
//! - [`TokenBucket`]: a rate with bursts, for the messages of one gateway and the requests of
//!   one API key.
//! - [`SignIns`]: failed sign-ins per source address and per user name at an address; after a
//!   few, each further failure makes the next attempt wait twice as long as the one before (1 s
//!   … 15 min), so guessing costs time and the logs stay quiet, while a person who mistyped
//!   waits at most seconds — and nobody's failures hold up anyone at another address.

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
/// bursts of `burst`. At most 100,000 addresses are followed; when full, the idle ones
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

    /// Whether an event from `peer` at `now` would be within its address's rate (nothing
    /// taken).
    pub fn within(&self, peer: &str, now: Instant) -> bool {
        self.buckets
            .get(&address_key(peer))
            .is_none_or(|b| b.tokens + b.refill(now) >= 1.0)
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

/// Failures of one name from one address before its attempts there have to wait.
const FREE_FAILURES: u32 = 5;
/// Failures from one address, whatever the name, before its attempts have to wait (more: an
/// office's people share one address).
const FREE_ADDRESS_FAILURES: u32 = 20;
/// The longest wait.
const MAX_WAIT: Duration = Duration::from_secs(15 * 60);
/// Failures older than this are forgotten.
const FORGET_AFTER: Duration = Duration::from_secs(3600);

#[derive(Debug, Clone, Copy)]
struct Failures {
    count: u32,
    /// Failures before attempts have to wait.
    free: u32,
    last: Instant,
}

impl Failures {
    /// When the next attempt may be made.
    fn next_at(&self) -> Instant {
        let over = self.count.saturating_sub(self.free);
        if over == 0 {
            return self.last;
        }
        let wait = Duration::from_secs(1u64 << (over - 1).min(20)).min(MAX_WAIT);
        self.last + wait
    }
}

/// Failed sign-ins by source address ([`address_key`]: an IPv6 /64 counts as one) and by
/// source address and user name. Nothing is counted per name alone: an outsider's failures,
/// from wherever, never make a person wait who signs in from another address (a user's
/// secret and an API key are 128 random bits: guessing them is hopeless at any rate, and
/// the per-address bound keeps the attempts' cost bounded). An attempt is counted as failed
/// when it begins ([`SignIns::begin`]) and forgotten when it succeeds, so a thousand parallel
/// attempts from one address are a thousand failures, not five checks each seeing none.
#[derive(Debug, Default)]
pub struct SignIns {
    failures: HashMap<String, Failures>,
}

/// Who tries to sign in: a user by name, or an API key (which has no name to count by).
#[derive(Debug, Clone, Copy)]
pub enum Attempt<'a> {
    /// User name and secret.
    User(&'a str),
    /// An API key.
    Key,
}

impl SignIns {
    /// The counts `attempt` from `address` is in, each with its failures before a wait.
    fn keys(attempt: Attempt, address: &str) -> Vec<(String, u32)> {
        let address = address_key(address);
        let mut keys = vec![(format!("address {address}"), FREE_ADDRESS_FAILURES)];
        if let Attempt::User(user) = attempt {
            keys.push((format!("user {user} at {address}"), FREE_FAILURES));
        }
        keys
    }

    /// Begin `attempt` from `address` at `now`: `Err(wait)` while it has to wait; otherwise it
    /// counts as a failure until [`SignIns::succeeded`] says otherwise.
    pub fn begin(&mut self, attempt: Attempt, address: &str, now: Instant) -> Result<(), Duration> {
        let keys = Self::keys(attempt, address);
        let wait = keys
            .iter()
            .filter_map(|(k, _)| self.failures.get(k))
            .filter(|f| now.saturating_duration_since(f.last) < FORGET_AFTER)
            .map(|f| f.next_at().saturating_duration_since(now))
            .max()
            .unwrap_or_default();
        if !wait.is_zero() {
            return Err(wait);
        }
        if self.failures.len() >= LIMIT {
            self.failures
                .retain(|_, f| now.saturating_duration_since(f.last) < FORGET_AFTER);
            if self.failures.len() >= LIMIT {
                self.failures.clear();
            }
        }
        for (key, free) in keys {
            let entry = self.failures.entry(key).or_insert(Failures {
                count: 0,
                free,
                last: now,
            });
            if now.saturating_duration_since(entry.last) >= FORGET_AFTER {
                entry.count = 0;
            }
            entry.count += 1;
            entry.last = now;
        }
        Ok(())
    }

    /// `attempt` from `address` succeeded: its failures start over.
    pub fn succeeded(&mut self, attempt: Attempt, address: &str) {
        for (key, _) in Self::keys(attempt, address) {
            self.failures.remove(&key);
        }
    }

    /// `attempt` from `address` could not be decided (the database, or too many checks at
    /// once): it does not count as a failure.
    pub fn undecided(&mut self, attempt: Attempt, address: &str) {
        for (key, _) in Self::keys(attempt, address) {
            if let Some(f) = self.failures.get_mut(&key) {
                f.count = f.count.saturating_sub(1);
            }
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
        let ann = Attempt::User("ann");
        for _ in 0..FREE_FAILURES {
            assert_eq!(s.begin(ann, "10.0.0.1:1", t0), Ok(()));
        }
        // The sixth failure of the name from the address: 1 s for it there, no one else.
        assert_eq!(s.begin(ann, "10.0.0.1:1", t0), Ok(()));
        assert_eq!(s.begin(ann, "10.0.0.1:2", t0), Err(Duration::from_secs(1)));
        assert_eq!(s.begin(ann, "10.0.0.2:1", t0), Ok(()), "from elsewhere");
        assert_eq!(s.begin(Attempt::User("bob"), "10.0.0.1:3", t0), Ok(()));
        assert_eq!(s.begin(Attempt::Key, "10.0.0.1:3", t0), Ok(()));
        let t1 = t0 + Duration::from_secs(1);
        assert_eq!(s.begin(ann, "10.0.0.1:1", t1), Ok(()));
        assert_eq!(s.begin(ann, "10.0.0.1:1", t1), Err(Duration::from_secs(2)));
        // Many more: at most 15 minutes.
        for n in 0..40 {
            s.begin(ann, "10.0.0.1:1", t1 + MAX_WAIT * n).ok();
        }
        // A second after the last: most of the longest wait ahead.
        let t2 = t1 + MAX_WAIT * 39 + Duration::from_secs(1);
        assert_eq!(
            s.begin(ann, "10.0.0.1:1", t2),
            Err(MAX_WAIT - Duration::from_secs(1))
        );
        // A success clears them; an hour without failures forgets them.
        s.succeeded(ann, "10.0.0.1:1");
        assert_eq!(s.begin(ann, "10.0.0.1:1", t2), Ok(()));
        s.succeeded(ann, "10.0.0.1:1");
        for _ in 0..=FREE_FAILURES {
            s.begin(Attempt::User("cy"), "10.0.0.3:1", t2).ok();
        }
        let later = t2 + FORGET_AFTER;
        assert_eq!(
            s.begin(Attempt::User("cy"), "10.0.0.3:1", later),
            Ok(()),
            "counted from one again"
        );
    }

    /// Wrong API keys from one address never hold up a right key from another, and many
    /// attempts at once from one address count as many (check and count are one step).
    #[test]
    fn an_address_holds_up_itself_alone_and_attempts_at_once_all_count() {
        let t0 = Instant::now();
        let mut s = SignIns::default();
        let tried = (0..600)
            .filter(|_| s.begin(Attempt::Key, "127.0.0.20:9", t0).is_ok())
            .count();
        assert_eq!(tried, FREE_ADDRESS_FAILURES as usize + 1);
        assert_eq!(s.begin(Attempt::Key, "127.0.0.21:9", t0), Ok(()));
        assert_eq!(s.begin(Attempt::User("ann"), "127.0.0.21:9", t0), Ok(()));
        // An IPv6 /64 is one address.
        for _ in 0..=FREE_ADDRESS_FAILURES {
            s.begin(Attempt::Key, "[2001:db8::1]:1", t0).ok();
        }
        assert!(s.begin(Attempt::Key, "[2001:db8::ffff]:1", t0).is_err());
        // An attempt the portal could not decide does not count.
        let mut u = SignIns::default();
        for _ in 0..100 {
            assert_eq!(u.begin(Attempt::Key, "10.1.1.1:1", t0), Ok(()));
            u.undecided(Attempt::Key, "10.1.1.1:1");
        }
    }
}
