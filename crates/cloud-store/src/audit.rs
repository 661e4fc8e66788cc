//! The audit log: every write to a lift, elevation and token operation (docs/PORTAL.md §Audit).

use sqlx::Row;

use cloud_types::audit::AuditEntry;

use crate::{Store, StoreError};

impl Store {
    /// Add an audit entry.
    pub async fn audit(&self, e: &AuditEntry) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO audit (at, account, lift, action, object, old_value, new_value, result) VALUES ($1, $2, $3, $4, $5, $6, $7, $8)",
        )
        .bind(e.at)
        .bind(&e.account)
        .bind(&e.lift)
        .bind(&e.action)
        .bind(&e.object)
        .bind(&e.old_value)
        .bind(&e.new_value)
        .bind(&e.result)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// The audit entries of `domain`'s lifts, newest first.
    pub async fn audit_log(&self, domain: &str) -> Result<Vec<AuditEntry>, StoreError> {
        let rows = sqlx::query(
            "SELECT a.* FROM audit a JOIN gateways g ON g.id = a.lift WHERE g.domain = $1 ORDER BY a.at DESC LIMIT 1000",
        )
        .bind(domain)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(AuditEntry {
                    at: r.try_get("at")?,
                    account: r.try_get("account")?,
                    lift: r.try_get("lift")?,
                    action: r.try_get("action")?,
                    object: r.try_get("object")?,
                    old_value: r.try_get("old_value")?,
                    new_value: r.try_get("new_value")?,
                    result: r.try_get("result")?,
                })
            })
            .collect::<Result<_, sqlx::Error>>()
            .map_err(StoreError::from)
    }
}
