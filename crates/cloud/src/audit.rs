//! Audit first (docs/PORTAL.md §Audit): what an operator asks of a lift — a write, an
//! elevation, a new token — is written to the audit log as intended before the lift is asked,
//! and completed with its outcome afterwards. When the intent cannot be written, nothing is
//! sent to the lift and the request is answered 503; an outcome that cannot be written at once
//! (the disk is full) waits in a queue and is written as soon as the database takes it, so a
//! write answered 2xx always has its complete entry.

use std::time::Duration;

use axum::http::StatusCode;
use cloud_store::Store;
use cloud_types::audit::AuditEntry;
use tokio::sync::mpsc;

use crate::errors::{error, ApiError};

/// Outcomes waiting for the database at most; beyond it an outcome is logged and its entry
/// stays `pending`.
const BACKLOG: usize = 4096;

/// An outcome to write: the entry's id, its result, the value before if read only now.
struct Outcome {
    id: i64,
    result: String,
    old_value: Option<String>,
}

/// The audit log as the API writes it.
#[derive(Clone)]
pub struct AuditTrail {
    store: Store,
    backlog: mpsc::Sender<Outcome>,
}

impl AuditTrail {
    /// The trail and the task that writes outcomes the database did not take at once.
    pub fn start(store: Store) -> (AuditTrail, tokio::task::JoinHandle<()>) {
        let (backlog, queued) = mpsc::channel(BACKLOG);
        let task = tokio::spawn(write_later(store.clone(), queued));
        (AuditTrail { store, backlog }, task)
    }

    /// Write `entry` as intended; its id. 503 when it cannot be written: then nothing may be
    /// sent to the lift.
    pub async fn intent(&self, entry: &AuditEntry) -> Result<i64, ApiError> {
        self.store.audit_intent(entry).await.map_err(|e| {
            tracing::error!(error = %e, lift = %entry.lift, action = %entry.action, "audit entry not written: nothing sent to the lift");
            error(
                StatusCode::SERVICE_UNAVAILABLE,
                format!("the audit log cannot be written ({e}): nothing was sent to the lift"),
            )
        })
    }

    /// Complete entry `id` with `result` (and `old_value`, if read only now): at once, or as
    /// soon as the database takes it.
    pub async fn outcome(&self, id: i64, result: String, old_value: Option<String>) {
        if let Err(e) = self
            .store
            .audit_outcome(id, &result, old_value.as_deref())
            .await
        {
            tracing::warn!(error = %e, id, "audit outcome waits for the database");
            let outcome = Outcome {
                id,
                result,
                old_value,
            };
            if self.backlog.try_send(outcome).is_err() {
                tracing::error!(id, "audit outcome lost: the entry stays pending");
            }
        }
    }

    /// Write `entry` complete (what the portal refused without asking the lift); a failure is
    /// logged, not answered: the refusal stands either way.
    pub async fn record(&self, entry: &AuditEntry) {
        if let Err(e) = self.store.audit(entry).await {
            tracing::error!(error = %e, lift = %entry.lift, "audit entry not written");
        }
    }
}

/// Write each queued outcome, trying again every second until the database takes it.
async fn write_later(store: Store, mut queued: mpsc::Receiver<Outcome>) {
    while let Some(o) = queued.recv().await {
        while let Err(e) = store
            .audit_outcome(o.id, &o.result, o.old_value.as_deref())
            .await
        {
            tracing::debug!(error = %e, id = o.id, "audit outcome still waits");
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
    }
}
