//! What gateway connections report beyond their values: bus events (docs/PROTOCOL.md
//! §Events) and changes of their connection, on a bounded queue to whoever keeps alarms
//! (docs/PORTAL.md §Alarms). The connections know nothing of alarms; the alarm service reads
//! the queue.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use nxg::msg::Event;
use tokio::sync::mpsc;

/// What a gateway connection reports.
#[derive(Debug, Clone, PartialEq)]
pub enum Report {
    /// A bus event of the lift.
    Event {
        /// The lift.
        lift: String,
        /// The event.
        event: Event,
    },
    /// The lift's gateway is connected.
    Online(String),
    /// The lift's gateway went away.
    Offline(String),
    /// The lift's state object now says it is in service or not (`[insights] state`); sent
    /// when that changes, and with the first value of a connection.
    Service {
        /// The lift.
        lift: String,
        /// In service.
        in_service: bool,
        /// When the value came (ms since the epoch).
        at: i64,
    },
    /// The lift pushed more than it may store per hour: `dropped` values not stored since its
    /// connection began (reported at most once a minute while it lasts).
    OverQuota {
        /// The lift.
        lift: String,
        /// Values not stored so far.
        dropped: u64,
    },
    /// The lift's gateway connected from another board (boardhashes `was` → `now`).
    BoardChanged {
        /// The lift.
        lift: String,
        /// The boardhash on record.
        was: String,
        /// The one the gateway sent.
        now: String,
    },
}

/// The connections' end of the queue of reports.
#[derive(Clone)]
pub struct Reports {
    tx: mpsc::Sender<Report>,
    dropped: Arc<AtomicU64>,
}

impl Reports {
    /// A queue of `capacity` reports, and its reading end.
    pub fn channel(capacity: usize) -> (Reports, mpsc::Receiver<Report>) {
        let (tx, rx) = mpsc::channel(capacity.max(1));
        let dropped = Arc::default();
        (Reports { tx, dropped }, rx)
    }

    /// Report a change of a lift's connection: it always waits for room (there are few).
    pub async fn report(&self, report: Report) {
        match report {
            Report::Event { .. } | Report::Service { .. } => self.offer(report),
            other => {
                let _ = self.tx.send(other).await;
            }
        }
    }

    /// Report `report` if there is room now; otherwise it is dropped (for reports that come
    /// again, such as a lift over its quota). Not `async`, as [`Reports::event`].
    pub fn try_report(&self, report: Report) {
        let _ = self.tx.try_send(report);
    }

    /// Report a bus event of `lift`, or drop and count it when the queue is full. Not `async`:
    /// a gateway connection's task calls it for every event it receives, and an awaited call
    /// would size that long-lived task by its future.
    pub fn event(&self, lift: String, event: Event) {
        self.offer(Report::Event { lift, event });
    }

    /// Report `report`, or drop and count it when the queue is full (as [`Reports::event`]).
    pub fn offer(&self, report: Report) {
        if self.tx.try_send(report).is_err() {
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
    }

    /// Reports dropped because the queue was full.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(Ordering::Relaxed)
    }
}
