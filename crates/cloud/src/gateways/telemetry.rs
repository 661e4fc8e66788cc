//! Telemetry: the values gateways push, written to the store in batches, rolled up per minute
//! and hour behind the writer, and deleted again after the retention time (as bus events are).
//! A value is counted as stored only once its batch is committed; every value not stored is
//! counted with the reason (docs/PORTAL.md §Metrics).

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{mpsc, watch};

use cloud_store::{Store, TelemetryRow};

/// Why a pushed value was not stored.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Dropped {
    /// The database could not take writes (full, unreachable) and the queue was full.
    Database,
    /// The database was slow and the value waited for room longer than [`PUSH_BACK_LIMIT`].
    Queue,
    /// The database refused the batch for what it held.
    Refused,
    /// The value is longer than `[gateways] max_value_bytes`.
    TooLarge,
    /// Nobody subscribed to the object: the gateway pushed it of its own.
    Unsubscribed,
    /// The lift stored more than `[gateways] max_stored_bytes_per_hour`.
    Quota,
    /// The portal was stopping: the writer had ended.
    Stopping,
}

impl Dropped {
    /// Every reason, in the order of [`TelemetryCounters::dropped`].
    pub const ALL: [Dropped; 7] = [
        Dropped::Database,
        Dropped::Queue,
        Dropped::Refused,
        Dropped::TooLarge,
        Dropped::Unsubscribed,
        Dropped::Quota,
        Dropped::Stopping,
    ];

    /// The `reason` label of `canlift_telemetry_dropped_total`.
    pub fn name(self) -> &'static str {
        match self {
            Dropped::Database => "database",
            Dropped::Queue => "queue",
            Dropped::Refused => "refused",
            Dropped::TooLarge => "too_large",
            Dropped::Unsubscribed => "unsubscribed",
            Dropped::Quota => "quota",
            Dropped::Stopping => "stopping",
        }
    }
}

/// Pushed values stored, and those not stored by why.
#[derive(Debug, Default)]
pub struct TelemetryCounters {
    /// Values committed to the database.
    pub stored: AtomicU64,
    /// Values not stored, by [`Dropped`] (in the order of [`Dropped::ALL`]).
    pub dropped: [AtomicU64; 7],
    /// Values a connection had to wait for room for (push-back: meanwhile it does not read
    /// its gateway's socket).
    pub waits: AtomicU64,
    /// Set while the writer cannot reach the database: connections then drop what does not
    /// fit at once instead of waiting for room that will not come soon.
    pub unreachable: AtomicBool,
}

impl TelemetryCounters {
    /// Count `n` values not stored for `why`.
    pub fn count_dropped(&self, why: Dropped, n: u64) {
        self.dropped[why as usize].fetch_add(n, Ordering::Relaxed);
    }

    /// Values not stored for `why`.
    pub fn dropped(&self, why: Dropped) -> u64 {
        self.dropped[why as usize].load(Ordering::Relaxed)
    }

    /// Values not stored, whatever the reason.
    pub fn dropped_total(&self) -> u64 {
        Dropped::ALL.iter().map(|&why| self.dropped(why)).sum()
    }
}

/// How long a connection waits for room in a full queue before it drops the value.
///
/// A database that is slow but working frees room within one batch (a full SQLite batch takes
/// well under a second); waiting longer would only hold the gateway's operator requests up.
pub const PUSH_BACK_LIMIT: Duration = Duration::from_secs(2);

/// The way into the telemetry writer: a bounded queue of pushed values.
///
/// When it is full the value's connection waits for room (at most [`PUSH_BACK_LIMIT`]) and
/// meanwhile reads nothing more from its gateway, so TCP slows the gateway down: an overloaded
/// portal spends its CPU on values it stores, not on reading and parsing values it would drop
/// (the gateway coalesces what changes meanwhile, the latest value wins). While the database is
/// unreachable values are dropped at once and counted.
#[derive(Clone)]
pub struct Queue {
    tx: mpsc::Sender<TelemetryRow>,
    counters: Arc<TelemetryCounters>,
}

impl Queue {
    /// A queue of `capacity` values and the writer's end of it.
    pub fn new(
        capacity: usize,
        counters: Arc<TelemetryCounters>,
    ) -> (Queue, mpsc::Receiver<TelemetryRow>) {
        let (tx, rx) = mpsc::channel(capacity.max(1));
        (Queue { tx, counters }, rx)
    }

    /// Values stored, dropped and waited for.
    pub fn counters(&self) -> &Arc<TelemetryCounters> {
        &self.counters
    }

    /// Values waiting for the writer.
    pub fn queued(&self) -> usize {
        self.tx.max_capacity() - self.tx.capacity()
    }

    /// Queue `row` if there is room now (or drop it, counted, when the database is
    /// unreachable or the writer gone); `Err(row)` when the caller should [`Queue::wait`].
    pub fn offer(&self, row: TelemetryRow) -> Result<(), TelemetryRow> {
        match self.tx.try_send(row) {
            Ok(()) => Ok(()),
            Err(mpsc::error::TrySendError::Full(row))
                if !self.counters.unreachable.load(Ordering::Relaxed) =>
            {
                Err(row)
            }
            Err(mpsc::error::TrySendError::Full(_)) => {
                self.counters.count_dropped(Dropped::Database, 1);
                Ok(())
            }
            Err(mpsc::error::TrySendError::Closed(_)) => {
                self.counters.count_dropped(Dropped::Stopping, 1);
                Ok(())
            }
        }
    }

    /// Wait for room for `row`, at most [`PUSH_BACK_LIMIT`]; dropped and counted after that.
    pub async fn wait(&self, row: TelemetryRow) {
        self.counters.waits.fetch_add(1, Ordering::Relaxed);
        match tokio::time::timeout(PUSH_BACK_LIMIT, self.tx.send(row)).await {
            Ok(Ok(())) => {}
            Ok(Err(_)) => self.counters.count_dropped(Dropped::Stopping, 1),
            Err(_) => self.counters.count_dropped(Dropped::Queue, 1),
        }
    }
}

/// Write telemetry in batches: what came within 200 ms of the first value, at most 16,384
/// values. Under load batches grow and each costs the database less per value (one commit, one
/// COPY, index pages touched once for many values); a quiet portal still stores within 200 ms.
///
/// While the database cannot take writes (unreachable, its disk full, busy) the batch in hand
/// is tried again (every 250 ms at first, then at most every 5 s: writing resumes within 5 s
/// of space or the server returning) and new values wait in the [`Queue`] in front of the
/// writer; once that is full the connections drop what they receive and count it
/// (`canlift_telemetry_dropped_total{reason="database"}`): a database that is only slow makes
/// them wait for room instead. A batch the database refuses for what it holds is dropped and
/// counted (`reason="refused"`). A value is counted as stored only when its batch committed.
/// A batch stored late (after waiting, or holding values that waited) has its minutes rolled
/// up again.
///
/// When `stop` turns true (the portal stops, its connections have ended) what is queued is
/// still written, then the writer ends.
pub async fn writer(
    store: Store,
    mut rx: mpsc::Receiver<TelemetryRow>,
    counters: Arc<TelemetryCounters>,
    mut stop: watch::Receiver<bool>,
    timer: crate::metrics::Timer,
) {
    const BATCH: usize = 16_384;
    let mut batch = Vec::with_capacity(BATCH);
    loop {
        // What waits is taken many at a time: their room is given back at once, so the
        // connections waiting for it are served together and then find room without waiting
        // (one at a time, room freed went value by value to the next waiter and every value
        // of a saturated portal waited).
        if super::next_batch(&mut rx, &mut batch, BATCH, &mut stop).await == 0 {
            return;
        }
        let deadline = tokio::time::Instant::now() + std::time::Duration::from_millis(200);
        while batch.len() < BATCH {
            let room = BATCH - batch.len();
            match tokio::time::timeout_at(deadline, rx.recv_many(&mut batch, room)).await {
                Ok(n) if n > 0 => {}
                _ => break,
            }
        }
        let mut retry = RETRY_FIRST;
        loop {
            match timer
                .statement("telemetry", batch.len(), store.telemetry(&batch))
                .await
            {
                Ok(()) => {
                    if retry > RETRY_FIRST {
                        counters.unreachable.store(false, Ordering::Relaxed);
                        tracing::info!(values = batch.len(), "telemetry stored again");
                    }
                    counters
                        .stored
                        .fetch_add(batch.len() as u64, Ordering::Relaxed);
                    break;
                }
                Err(e) if e.is_unavailable() => {
                    if retry == RETRY_FIRST {
                        counters.unreachable.store(true, Ordering::Relaxed);
                        let trouble = e.trouble().map(|t| t.to_string()).unwrap_or_default();
                        tracing::error!(error = %e, %trouble, values = batch.len(), "the database takes no writes: telemetry waits");
                    }
                    tokio::time::sleep(retry).await;
                    retry = (retry * 2).min(RETRY_LAST);
                }
                Err(e) => {
                    tracing::error!(error = %e, values = batch.len(), "telemetry not stored");
                    counters.count_dropped(Dropped::Refused, batch.len() as u64);
                    break;
                }
            }
        }
        // Values that waited (here, or in the queue behind a batch that did) may belong to
        // minutes already rolled up.
        let late = cloud_types::now_ms() - cloud_store::rollups::LAG_MS;
        if let Some(oldest) = batch.iter().map(|r| r.at).min().filter(|&at| at < late) {
            store.rewind_roll_ups(oldest);
        }
        batch.clear();
    }
}

const RETRY_FIRST: std::time::Duration = std::time::Duration::from_millis(250);
const RETRY_LAST: std::time::Duration = std::time::Duration::from_secs(5);

/// Roll up the pushed values once a minute (docs/PORTAL.md §History), at once again while
/// behind (a portal started after a pause, or minutes made again after an outage).
pub async fn roll_up(store: Store) {
    let mut every_minute = tokio::time::interval(Duration::from_secs(60));
    every_minute.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        every_minute.tick().await;
        loop {
            let started = std::time::Instant::now();
            match store.roll_up(cloud_types::now_ms()).await {
                Ok(rolled) if rolled.values > 0 => {
                    tracing::debug!(
                        values = rolled.values,
                        minutes = rolled.minutes,
                        hours = rolled.hours,
                        took_ms = started.elapsed().as_millis() as u64,
                        "values rolled up"
                    );
                    // A full round may have left more behind it.
                    tokio::task::yield_now().await;
                }
                Ok(_) => break,
                Err(e) => {
                    tracing::warn!(error = %e, "values not rolled up: tried again in a minute");
                    break;
                }
            }
        }
    }
}

/// What is deleted after its retention time.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Retained {
    /// Pushed values (`[database] telemetry_days`).
    Telemetry,
    /// Their roll-ups and the lifts' status changes (`[database] rollup_days`).
    RollUps,
    /// Bus events (`[database] events_days`).
    Events,
    /// Refused CONNECTs (`[gateways] refused_keep_days`, and all but the newest
    /// `refused_keep_rows`).
    Refused {
        /// Rows kept at most.
        rows: u32,
    },
    /// Outcomes of writes made with an `Idempotency-Key` (a day).
    Idempotency,
}

impl Retained {
    /// What the log calls it.
    pub fn name(self) -> &'static str {
        match self {
            Retained::Telemetry => "telemetry",
            Retained::RollUps => "roll-ups",
            Retained::Events => "events",
            Retained::Refused { .. } => "refused",
            Retained::Idempotency => "idempotency",
        }
    }
}

/// Delete `kept` rows older than `days` once an hour (and at start); 0 days keeps everything.
/// In a cluster, one process at a time ([`Store::turn`]): the others' rounds found the same
/// rows and waited for each other's locks on them.
pub async fn retention(kept: Retained, store: Store, days: u32) {
    if days == 0 {
        return;
    }
    let job = format!("retention {}", kept.name());
    let mut hourly = tokio::time::interval(std::time::Duration::from_secs(3600));
    loop {
        hourly.tick().await;
        let turn = match store.turn(&job).await {
            Ok(Some(turn)) => turn,
            // Another process deletes them now.
            Ok(None) => continue,
            Err(e) => {
                tracing::error!(error = %e, kept = kept.name(), "old rows not deleted");
                continue;
            }
        };
        let before = cloud_types::now_ms() - i64::from(days) * 86_400_000;
        let deleted = match kept {
            Retained::Telemetry => store.forget_telemetry(before).await,
            // Status changes are few and reports reach as far back as the roll-ups.
            Retained::RollUps => match store.forget_roll_ups(before).await {
                Ok(n) => store.forget_statuses(before).await.map(|m| n + m),
                failed => failed,
            },
            Retained::Events => store.forget_events(before).await,
            Retained::Refused { rows } => store.forget_refused(before, rows).await,
            Retained::Idempotency => store.forget_idempotency(cloud_types::now_ms()).await,
        };
        turn.end().await;
        match deleted {
            Ok(0) => {}
            Ok(n) => tracing::info!(rows = n, days, kept = kept.name(), "old rows deleted"),
            Err(e) => tracing::error!(error = %e, kept = kept.name(), "old rows not deleted"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(value: u32) -> TelemetryRow {
        TelemetryRow {
            lift: "1050-4097-TEST-000001".into(),
            mplex: "0x652001".into(),
            node: 0,
            value: value.to_string(),
            at: 0,
        }
    }

    fn count(c: &AtomicU64) -> u64 {
        c.load(Ordering::Relaxed)
    }

    #[tokio::test(start_paused = true)]
    async fn a_full_queue_makes_the_connection_wait_not_drop() {
        let (queue, mut rx) = Queue::new(1, Arc::default());
        assert!(queue.offer(row(1)).is_ok());
        let second = queue.offer(row(2)).expect_err("no room: wait");
        let waiting = tokio::spawn({
            let queue = queue.clone();
            async move { queue.wait(second).await }
        });
        tokio::time::sleep(PUSH_BACK_LIMIT / 2).await;
        assert!(!waiting.is_finished(), "waits while the queue is full");
        assert_eq!(rx.recv().await.map(|r| r.value), Some("1".into()));
        waiting.await.expect("the wait ends");
        assert_eq!(rx.recv().await.map(|r| r.value), Some("2".into()));
        let c = queue.counters();
        assert_eq!((count(&c.waits), c.dropped_total()), (1, 0));
    }

    #[tokio::test(start_paused = true)]
    async fn a_wait_ends_after_the_limit_with_the_value_dropped() {
        let (queue, mut rx) = Queue::new(1, Arc::default());
        assert!(queue.offer(row(1)).is_ok());
        let second = queue.offer(row(2)).expect_err("no room: wait");
        let started = tokio::time::Instant::now();
        queue.wait(second).await;
        assert_eq!(started.elapsed(), PUSH_BACK_LIMIT);
        assert_eq!(queue.counters().dropped(Dropped::Queue), 1);
        assert_eq!(rx.recv().await.map(|r| r.value), Some("1".into()));
        assert!(rx.try_recv().is_err(), "the late value is not queued");
    }

    /// A stopping portal: what is queued is written, then the writer ends although the
    /// queue still has senders; a value offered after that is dropped, not queued.
    #[tokio::test]
    async fn a_stopped_writer_writes_what_is_queued_and_ends() {
        let store = Store::open("sqlite::memory:").await.unwrap();
        let (queue, rx) = Queue::new(100, Arc::default());
        for value in 0..50 {
            assert!(queue.offer(row(value)).is_ok());
        }
        let (stop, stopping) = watch::channel(false);
        stop.send_replace(true);
        writer(
            store.clone(),
            rx,
            queue.counters().clone(),
            stopping,
            Default::default(),
        )
        .await;
        assert_eq!(count(&queue.counters().stored), 50);
        let stored = store
            .values("1050-4097-TEST-000001", "0x652001", 0, i64::MAX, 1000)
            .await
            .unwrap();
        assert_eq!(stored.len(), 50);
        assert!(queue.offer(row(50)).is_ok(), "no writer any more: dropped");
        assert_eq!(queue.counters().dropped(Dropped::Stopping), 1);
    }

    #[tokio::test]
    async fn an_unreachable_database_or_a_gone_writer_drops_at_once() {
        let (queue, rx) = Queue::new(1, Arc::default());
        assert!(queue.offer(row(1)).is_ok());
        queue.counters().unreachable.store(true, Ordering::Relaxed);
        assert!(queue.offer(row(2)).is_ok(), "dropped, not handed back");
        assert_eq!(queue.counters().dropped(Dropped::Database), 1);
        queue.counters().unreachable.store(false, Ordering::Relaxed);
        assert!(queue.offer(row(3)).is_err(), "reachable again: wait");
        drop(rx);
        assert!(queue.offer(row(4)).is_ok(), "no writer: dropped");
        assert_eq!(queue.counters().dropped(Dropped::Stopping), 1);
        assert_eq!(queue.counters().dropped_total(), 2);
    }
}
