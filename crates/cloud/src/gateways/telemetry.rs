//! Telemetry: the values gateways push, written to the store in batches, and deleted again
//! after the retention time (as bus events are).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use tokio::sync::mpsc;

use crate::store::{self, Store, TelemetryRow};

/// Pushed values stored, and dropped because the database could not keep up (the queue in
/// front of it was full) or failed.
#[derive(Debug, Default)]
pub struct TelemetryCounters {
    /// Values written.
    pub stored: AtomicU64,
    /// Values lost.
    pub dropped: AtomicU64,
}

/// Write telemetry in batches: what came within 200 ms of the first value, at most 16,384
/// values. Under load batches grow and each costs the database less per value (one commit, one
/// COPY, index pages touched once for many values); a quiet portal still stores within 200 ms.
///
/// While the database cannot be reached the batch in hand is tried again (every 250 ms at
/// first, then at most every 5 s) and new values wait in the channel in front of the writer;
/// once that is full the connections drop what they receive and count it
/// (`canlift_telemetry_dropped_total`). A batch the database refuses is dropped and counted.
pub async fn writer(
    store: Store,
    mut rx: mpsc::Receiver<TelemetryRow>,
    counters: Arc<TelemetryCounters>,
) {
    const BATCH: usize = 16_384;
    let mut batch = Vec::with_capacity(BATCH);
    loop {
        let first = rx.recv().await;
        let Some(first) = first else {
            return;
        };
        batch.push(first);
        let deadline = tokio::time::Instant::now() + std::time::Duration::from_millis(200);
        while batch.len() < BATCH {
            match tokio::time::timeout_at(deadline, rx.recv()).await {
                Ok(Some(v)) => batch.push(v),
                _ => break,
            }
        }
        let mut retry = RETRY_FIRST;
        let counter = loop {
            match store.telemetry(&batch).await {
                Ok(()) => {
                    if retry > RETRY_FIRST {
                        tracing::info!(values = batch.len(), "telemetry stored again");
                    }
                    break &counters.stored;
                }
                Err(e) if e.is_unavailable() => {
                    if retry == RETRY_FIRST {
                        tracing::error!(error = %e, values = batch.len(), "database unreachable: telemetry waits");
                    }
                    tokio::time::sleep(retry).await;
                    retry = (retry * 2).min(RETRY_LAST);
                }
                Err(e) => {
                    tracing::error!(error = %e, values = batch.len(), "telemetry not stored");
                    break &counters.dropped;
                }
            }
        };
        counter.fetch_add(batch.len() as u64, Ordering::Relaxed);
        batch.clear();
    }
}

const RETRY_FIRST: std::time::Duration = std::time::Duration::from_millis(250);
const RETRY_LAST: std::time::Duration = std::time::Duration::from_secs(5);

/// What is deleted after its retention time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kept {
    /// Pushed values (`[database] telemetry_days`).
    Telemetry,
    /// Bus events (`[database] events_days`).
    Events,
}

/// Delete `kept` rows older than `days` once an hour (and at start); 0 days keeps everything.
pub async fn retention(kept: Kept, store: Store, days: u32) {
    if days == 0 {
        return;
    }
    let mut hourly = tokio::time::interval(std::time::Duration::from_secs(3600));
    loop {
        hourly.tick().await;
        let before = store::now_ms() - i64::from(days) * 86_400_000;
        let deleted = match kept {
            Kept::Telemetry => store.forget_telemetry(before).await,
            Kept::Events => store.forget_events(before).await,
        };
        match deleted {
            Ok(0) => {}
            Ok(n) => tracing::info!(rows = n, days, ?kept, "old rows deleted"),
            Err(e) => tracing::error!(error = %e, ?kept, "old rows not deleted"),
        }
    }
}
