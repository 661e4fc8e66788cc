//! The TLS session-ticket keys of a portal cluster (docs/CLUSTER.md §TLS sessions): one row, so
//! that every process opens the tickets of every other. Replaced only over the version read,
//! so that of two processes rotating at once one wins and both use its keys.

use sqlx::Row;

use super::{Store, StoreError};

impl Store {
    /// The shared ticket keys and their version, once someone made them.
    pub async fn ticket_keys(&self) -> Result<Option<(String, i64)>, StoreError> {
        let row = sqlx::query("SELECT keys, version FROM tls_ticket_keys WHERE id = 1")
            .fetch_optional(&self.pool)
            .await?;
        row.map(|r| Ok((r.try_get("keys")?, r.try_get("version")?)))
            .transpose()
            .map_err(|e: sqlx::Error| StoreError::from(e))
    }

    /// Replace the keys of `version` (`None`: there are none yet) by `keys`; whether this call
    /// did (`false`: another process changed them first).
    pub async fn replace_ticket_keys(
        &self,
        keys: &str,
        version: Option<i64>,
    ) -> Result<bool, StoreError> {
        let done = match version {
            None => {
                sqlx::query(
                    "INSERT INTO tls_ticket_keys (id, keys, version) VALUES (1, $1, 1) \
                 ON CONFLICT (id) DO NOTHING",
                )
                .bind(keys)
                .execute(&self.pool)
                .await?
            }
            Some(version) => {
                sqlx::query(
                    "UPDATE tls_ticket_keys SET keys = $1, version = version + 1 \
                 WHERE id = 1 AND version = $2",
                )
                .bind(keys)
                .bind(version)
                .execute(&self.pool)
                .await?
            }
        };
        Ok(done.rows_affected() == 1)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Run by the store's tests on SQLite and PostgreSQL: the first maker wins, a replacement
    /// over a stale version does nothing.
    pub(crate) async fn made_once_replaced_over_the_version(store: &Store) {
        assert_eq!(store.ticket_keys().await.unwrap(), None);
        assert!(store.replace_ticket_keys("a", None).await.unwrap());
        assert!(!store.replace_ticket_keys("b", None).await.unwrap());
        assert_eq!(store.ticket_keys().await.unwrap(), Some(("a".into(), 1)));
        assert!(store.replace_ticket_keys("c", Some(1)).await.unwrap());
        assert!(!store.replace_ticket_keys("d", Some(1)).await.unwrap());
        assert_eq!(store.ticket_keys().await.unwrap(), Some(("c".into(), 2)));
    }
}
