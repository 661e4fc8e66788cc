//! Outcomes of writes made with an `Idempotency-Key` (the IETF httpapi draft's header): the
//! same key of the same credential within a day answers the first outcome again, without a
//! second write (docs/PORTAL.md §Idempotency).

use sqlx::Row;

use crate::{Store, StoreError};

/// How long a key's outcome is kept (ms).
pub const KEPT_MS: i64 = 24 * 3_600_000;

/// What a key says about a request.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Idempotent {
    /// A new key: the request is carried out; its outcome is recorded with
    /// [`Store::idempotency_finish`] (or the key given up with [`Store::idempotency_forget`]).
    New,
    /// The key was used for this request before: its outcome.
    Done {
        /// The HTTP status.
        status: u16,
        /// The body (JSON).
        body: String,
    },
    /// The first request with the key has not finished yet.
    InProgress,
    /// The key was used for another request (other method, path or body).
    Mismatch,
}

impl Store {
    /// Claim `key` of `scope` (whose credential) for a request whose fingerprint (digest of
    /// method, path and body) is `fingerprint`, at `now` (ms). A key older than a day is new
    /// again.
    pub async fn idempotency_begin(
        &self,
        scope: &str,
        key: &str,
        fingerprint: &str,
        now: i64,
    ) -> Result<Idempotent, StoreError> {
        sqlx::query("DELETE FROM idempotency WHERE scope = $1 AND key = $2 AND created < $3")
            .bind(scope)
            .bind(key)
            .bind(now - KEPT_MS)
            .execute(&self.pool)
            .await?;
        let claimed = sqlx::query(
            "INSERT INTO idempotency (scope, key, fingerprint, status, body, created) VALUES ($1, $2, $3, NULL, NULL, $4) \
             ON CONFLICT (scope, key) DO NOTHING",
        )
        .bind(scope)
        .bind(key)
        .bind(fingerprint)
        .bind(now)
        .execute(&self.pool)
        .await?;
        if claimed.rows_affected() == 1 {
            return Ok(Idempotent::New);
        }
        let row = sqlx::query(
            "SELECT fingerprint, status, body FROM idempotency WHERE scope = $1 AND key = $2",
        )
        .bind(scope)
        .bind(key)
        .fetch_optional(&self.pool)
        .await?;
        let Some(row) = row else {
            // Deleted in between by its own request giving it up: as good as new once more.
            return Ok(Idempotent::InProgress);
        };
        let recorded: String = row.try_get("fingerprint")?;
        if recorded != fingerprint {
            return Ok(Idempotent::Mismatch);
        }
        let status: Option<i64> = row.try_get("status")?;
        let body: Option<String> = row.try_get("body")?;
        Ok(match (status, body) {
            (Some(status), Some(body)) => Idempotent::Done {
                status: u16::try_from(status).unwrap_or(500),
                body,
            },
            _ => Idempotent::InProgress,
        })
    }

    /// Record the outcome of the request that claimed `key`.
    pub async fn idempotency_finish(
        &self,
        scope: &str,
        key: &str,
        status: u16,
        body: &str,
    ) -> Result<(), StoreError> {
        sqlx::query("UPDATE idempotency SET status = $1, body = $2 WHERE scope = $3 AND key = $4")
            .bind(i64::from(status))
            .bind(body)
            .bind(scope)
            .bind(key)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Give `key` up: its request changed nothing (refused before reaching anything), so the
    /// key may be used again.
    pub async fn idempotency_forget(&self, scope: &str, key: &str) -> Result<(), StoreError> {
        sqlx::query("DELETE FROM idempotency WHERE scope = $1 AND key = $2")
            .bind(scope)
            .bind(key)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Delete the outcomes older than a day before `now`; how many went.
    pub async fn forget_idempotency(&self, now: i64) -> Result<u64, StoreError> {
        Ok(sqlx::query("DELETE FROM idempotency WHERE created < $1")
            .bind(now - KEPT_MS)
            .execute(&self.pool)
            .await?
            .rows_affected())
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Run by the store's tests on SQLite and PostgreSQL.
    pub(crate) async fn a_key_answers_its_first_outcome(store: &Store) {
        let now = 10 * KEPT_MS;
        let begin = |key, fingerprint, at| store.idempotency_begin("scope", key, fingerprint, at);
        assert_eq!(begin("k1", "put A", now).await.unwrap(), Idempotent::New);
        assert_eq!(
            begin("k1", "put A", now).await.unwrap(),
            Idempotent::InProgress
        );
        assert_eq!(
            begin("k1", "put B", now).await.unwrap(),
            Idempotent::Mismatch
        );
        store
            .idempotency_finish("scope", "k1", 200, "{\"ok\":1}")
            .await
            .unwrap();
        assert_eq!(
            begin("k1", "put A", now + 1000).await.unwrap(),
            Idempotent::Done {
                status: 200,
                body: "{\"ok\":1}".into()
            }
        );
        // Another credential's key of the same name is its own.
        assert_eq!(
            store
                .idempotency_begin("other", "k1", "put A", now)
                .await
                .unwrap(),
            Idempotent::New
        );
        // Given up: new again; a day later: new again.
        store.idempotency_forget("other", "k1").await.unwrap();
        assert_eq!(
            store
                .idempotency_begin("other", "k1", "put A", now)
                .await
                .unwrap(),
            Idempotent::New
        );
        assert_eq!(
            begin("k1", "put A", now + KEPT_MS + 1).await.unwrap(),
            Idempotent::New
        );
        assert_eq!(
            store.forget_idempotency(now + 3 * KEPT_MS).await.unwrap(),
            2
        );
    }
}
