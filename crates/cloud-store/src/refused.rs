//! Refused connection attempts: which lift, from where, why.

use sqlx::Row;

use cloud_types::now_ms;

use crate::{Store, StoreError};

impl Store {
    /// Record a refused connection attempt.
    pub async fn refused(&self, lift: &str, peer: &str, cause: &str) -> Result<(), StoreError> {
        sqlx::query("INSERT INTO refused (at, lift, peer, cause) VALUES ($1, $2, $3, $4)")
            .bind(now_ms())
            .bind(lift)
            .bind(peer)
            .bind(cause)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Refused attempts for a lift, newest first: (at, peer, cause).
    pub async fn refusals(&self, lift: &str) -> Result<Vec<(i64, String, String)>, StoreError> {
        let rows =
            sqlx::query("SELECT at, peer, cause FROM refused WHERE lift = $1 ORDER BY at DESC")
                .bind(lift)
                .fetch_all(&self.pool)
                .await?;
        rows.iter()
            .map(|r| Ok((r.try_get("at")?, r.try_get("peer")?, r.try_get("cause")?)))
            .collect()
    }
}
