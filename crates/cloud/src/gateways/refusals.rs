//! Refused CONNECTs (docs/PORTAL.md §Refused gateways): each recorded with the portal's reason
//! and a digest of the domain token offered, never the sender's text, and logged — at most a
//! few a second from one source address (and one IPv6 /64); the rest only counted. A sender of
//! thousands of CONNECTs fills neither the disk nor the log.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Mutex, PoisonError};
use std::time::Instant;

use cloud_store::{Refusal, Store};

use crate::throttle::AddressRates;

/// Refusals recorded and logged per second and source address, on average.
const PER_ADDRESS_PER_S: f64 = 2.0;
/// … with bursts of this many.
const PER_ADDRESS_BURST: f64 = 10.0;

/// Where refused CONNECTs go.
pub struct Refusals {
    store: Store,
    rates: Mutex<AddressRates>,
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
            recorded: AtomicU64::new(0),
            unrecorded: AtomicU64::new(0),
        }
    }

    /// `lift`'s CONNECT from `peer`, offering domain token `domain`, was refused for `cause`.
    pub async fn note(&self, lift: &str, peer: &str, cause: &str, domain: &str) {
        let within = self
            .rates
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .take(peer, Instant::now());
        if !within {
            self.unrecorded.fetch_add(1, Ordering::Relaxed);
            return;
        }
        self.recorded.fetch_add(1, Ordering::Relaxed);
        tracing::warn!(%lift, %peer, %cause, "gateway refused");
        if let Err(e) = self
            .store
            .refused(&Refusal::now(lift, peer, cause, domain))
            .await
        {
            tracing::debug!(error = %e, "refusal not recorded");
        }
    }
}
