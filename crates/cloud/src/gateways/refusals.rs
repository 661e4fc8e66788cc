//! Refused CONNECTs (docs/PORTAL.md §Refused gateways): each counted by its reason, recorded
//! with the portal's cause and a digest of the domain token offered — never the sender's text
//! — and logged, at most a few a second from one source address (and one IPv6 /64); the rest
//! only counted. An address whose CONNECTs keep being refused is, while it keeps on, turned
//! away before any TLS work ([`Refusals::admits`]). A sender of thousands of CONNECTs fills
//! neither the disk nor the log, nor the cores with handshakes.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, PoisonError};
use std::time::Instant;

use cloud_store::{Refusal, Store};

use crate::throttle::AddressRates;

/// Refusals recorded and logged per second and source address, on average.
const PER_ADDRESS_PER_S: f64 = 2.0;
/// … with bursts of this many.
const PER_ADDRESS_BURST: f64 = 10.0;

/// Refused CONNECTs per source address and second an address may have, on average, before its
/// connections are closed before the TLS handshake: one every two seconds — a misconfigured
/// gateway backs off far more slowly, and a site of many lifts behind one address has room —
/// with bursts of [`GUARD_BURST`].
const GUARD_PER_S: f64 = 0.5;
/// … with bursts of this many (a fleet behind one address reconnecting with a wrong domain).
const GUARD_BURST: f64 = 60.0;

/// Invalid CONNECTs logged per source address: one a minute.
const INVALID_LOGGED_PER_S: f64 = 1.0 / 60.0;

/// Why a CONNECT was refused, as `/metrics` counts it (`canlift_gateways_refused_total`'s
/// `reason`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Reason {
    /// No account has the domain token.
    Domain,
    /// A wrong cloud token, or none where one was issued.
    Token,
    /// A valid token from another board, refused by `boardhash_change = "refuse"`.
    Board,
    /// The identity is malformed: a control, format or private-use character, not NFC, too
    /// long (docs/PROTOCOL.md §Connection).
    Identity,
    /// Another account's first contact of the same identity took its key at the same moment.
    Taken,
    /// The source address kept sending refused CONNECTs: closed before the TLS handshake.
    Address,
}

impl Reason {
    /// Every reason, in the order of the counters.
    pub const ALL: [Reason; 6] = [
        Reason::Domain,
        Reason::Token,
        Reason::Board,
        Reason::Identity,
        Reason::Taken,
        Reason::Address,
    ];

    /// The `reason` label.
    pub fn name(self) -> &'static str {
        match self {
            Reason::Domain => "domain",
            Reason::Token => "token",
            Reason::Board => "board",
            Reason::Identity => "identity",
            Reason::Taken => "taken",
            Reason::Address => "address",
        }
    }
}

/// Where refused CONNECTs go.
pub struct Refusals {
    store: Store,
    /// Refusals recorded and logged per address.
    rates: Mutex<AddressRates>,
    /// Refusals an address may have before its connections are turned away unencrypted.
    guard: Mutex<AddressRates>,
    /// Invalid CONNECTs logged per address.
    invalid_logged: Mutex<AddressRates>,
    /// Refused, by [`Reason`] (in the order of [`Reason::ALL`]).
    refused: [AtomicU64; Reason::ALL.len()],
    /// Refusals recorded and logged.
    pub recorded: AtomicU64,
    /// Refusals over their address's rate: only counted.
    pub unrecorded: AtomicU64,
}

impl Refusals {
    /// Refusals recorded in `store`.
    pub fn new(store: Store) -> Refusals {
        Refusals {
            store,
            rates: Mutex::new(AddressRates::new(PER_ADDRESS_PER_S, PER_ADDRESS_BURST)),
            guard: Mutex::new(AddressRates::new(GUARD_PER_S, GUARD_BURST)),
            invalid_logged: Mutex::new(AddressRates::new(INVALID_LOGGED_PER_S, 1.0)),
            refused: Default::default(),
            recorded: AtomicU64::new(0),
            unrecorded: AtomicU64::new(0),
        }
    }

    /// Whether a connection from `peer` may go on to the TLS handshake: not while its address
    /// has had more refused CONNECTs than one every two seconds allows (counted as refused for
    /// [`Reason::Address`]).
    pub fn admits(&self, peer: &str) -> bool {
        let admitted = lock(&self.guard).within(peer, Instant::now());
        if !admitted {
            self.count(Reason::Address);
        }
        admitted
    }

    /// `lift`'s CONNECT from `peer`, offering domain token `domain`, was refused for `reason`
    /// (`cause` in words).
    pub async fn note(&self, lift: &str, peer: &str, reason: Reason, cause: &str, domain: &str) {
        self.count(reason);
        let now = Instant::now();
        lock(&self.guard).take(peer, now);
        if !lock(&self.rates).take(peer, now) {
            self.unrecorded.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.recorded.fetch_add(1, Ordering::Relaxed);
        tracing::warn!(%lift, %peer, reason = reason.name(), %cause, "gateway refused");
        if let Err(e) = self
            .store
            .refused(&Refusal::now(lift, peer, cause, domain))
            .await
        {
            tracing::debug!(error = %e, "refusal not recorded");
        }
    }

    /// A CONNECT from `peer` was malformed (`why`): counted, and logged once a minute per
    /// address at most (its text is the sender's, so it is not recorded).
    pub fn invalid(&self, peer: &str, why: &str) {
        self.count(Reason::Identity);
        let now = Instant::now();
        lock(&self.guard).take(peer, now);
        if lock(&self.invalid_logged).take(peer, now) {
            tracing::warn!(%peer, %why, "invalid CONNECT refused (logged once a minute per address)");
        }
    }

    /// Refused CONNECTs by reason, for `/metrics`.
    pub fn counts(&self) -> Vec<(Reason, u64)> {
        Reason::ALL
            .iter()
            .zip(&self.refused)
            .map(|(r, n)| (*r, n.load(Ordering::Relaxed)))
            .collect()
    }

    fn count(&self, reason: Reason) {
        if let Some(i) = Reason::ALL.iter().position(|r| *r == reason) {
            self.refused[i].fetch_add(1, Ordering::Relaxed);
        }
    }
}

fn lock(rates: &Mutex<AddressRates>) -> std::sync::MutexGuard<'_, AddressRates> {
    rates.lock().unwrap_or_else(PoisonError::into_inner)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An address with a burst of refusals is turned away before TLS, alone, and counted.
    #[tokio::test]
    async fn an_address_that_keeps_being_refused_is_turned_away_alone() {
        let refusals = Refusals::new(Store::open("sqlite::memory:").await.unwrap());
        for _ in 0..GUARD_BURST as usize {
            assert!(refusals.admits("192.0.2.9:1000"));
            refusals.invalid("192.0.2.9:1000", "sernum holds a format character");
        }
        assert!(!refusals.admits("192.0.2.9:1001"));
        assert!(refusals.admits("192.0.2.10:1000"), "another address");
        let counts = refusals.counts();
        assert!(counts.contains(&(Reason::Identity, GUARD_BURST as u64)));
        assert!(counts.contains(&(Reason::Address, 1)));
    }
}
