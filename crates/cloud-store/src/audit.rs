//! The audit log: every write to a lift, elevation and token operation (docs/PORTAL.md §Audit).
//! What an operator asks of a lift is written as intended before the lift is asked
//! ([`Store::audit_intent`]) and completed with its outcome afterwards
//! ([`Store::audit_outcome`]); what the portal or an administrator does alone is written once
//! ([`Store::audit`]).

use sqlx::Row;

use cloud_types::audit::AuditEntry;

use crate::{new_id, Store, StoreError};

impl Store {
    /// Add an audit entry.
    pub async fn audit(&self, e: &AuditEntry) -> Result<(), StoreError> {
        self.insert_audit(new_id(), e).await
    }

    /// Write `e` as intended, before the lift is asked; its id, for [`Store::audit_outcome`].
    /// When this fails nothing may be sent to the lift.
    pub async fn audit_intent(&self, e: &AuditEntry) -> Result<i64, StoreError> {
        let id = new_id();
        self.insert_audit(id, e).await?;
        Ok(id)
    }

    /// Complete entry `id` with what became of it (`result`), and the value before where it
    /// was read only then.
    pub async fn audit_outcome(
        &self,
        id: i64,
        result: &str,
        old_value: Option<&str>,
    ) -> Result<(), StoreError> {
        let done = sqlx::query(
            "UPDATE audit SET result = $1, old_value = COALESCE($2, old_value) WHERE id = $3",
        )
        .bind(result)
        .bind(old_value)
        .bind(id)
        .execute(&self.pool)
        .await
        .map(|_| ())
        .map_err(StoreError::from);
        self.health().note(&done);
        done
    }

    async fn insert_audit(&self, id: i64, e: &AuditEntry) -> Result<(), StoreError> {
        let done = sqlx::query(
            "INSERT INTO audit (id, at, account, lift, action, object, old_value, new_value, result, address, owner) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, \
             (SELECT a.name FROM gateways g JOIN accounts a ON a.domain = g.domain WHERE g.id = $4))",
        )
        .bind(id)
        .bind(e.at)
        .bind(&e.account)
        .bind(&e.lift)
        .bind(&e.action)
        .bind(&e.object)
        .bind(&e.old_value)
        .bind(&e.new_value)
        .bind(&e.result)
        .bind(&e.address)
        .execute(&self.pool)
        .await
        .map(|_| ())
        .map_err(StoreError::from);
        self.health().note(&done);
        done
    }

    /// The audit entries of `domain`'s lifts, newest first: those written while the lift was
    /// the account's (a retired lift's entries stay the account's; its key may later be
    /// another's), each lift named by the id the account sees.
    pub async fn audit_log(&self, domain: &str) -> Result<Vec<AuditEntry>, StoreError> {
        let rows = sqlx::query(
            "SELECT * FROM audit WHERE owner = (SELECT name FROM accounts WHERE domain = $1) ORDER BY at DESC LIMIT 1000",
        )
        .bind(domain)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(AuditEntry {
                    at: r.try_get("at")?,
                    account: r.try_get("account")?,
                    lift: cloud_types::lifts::shown_id(&r.try_get::<String, _>("lift")?).to_owned(),
                    action: r.try_get("action")?,
                    object: r.try_get("object")?,
                    old_value: r.try_get("old_value")?,
                    new_value: r.try_get("new_value")?,
                    result: r.try_get("result")?,
                    address: r.try_get("address")?,
                })
            })
            .collect::<Result<_, sqlx::Error>>()
            .map_err(StoreError::from)
    }
}
