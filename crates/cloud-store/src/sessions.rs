//! Browser sessions of the web UI, by the SHA-256 digest of their cookie: any process of a
//! cluster (or the portal after a restart) knows them.

use sqlx::Row;

use crate::{Store, StoreError};

/// A browser session as the database keeps it (docs/PORTAL.md §Web UI): what it was opened
/// with — an API key's digest or a user's name — its CSRF token, and when it was last used.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SessionRecord {
    /// The digest of the API key it was opened with.
    pub key_digest: Option<String>,
    /// The user who signed in with name and secret: (account, name).
    pub user: Option<(String, String)>,
    /// The session's CSRF token.
    pub csrf: String,
    /// ms since the Unix epoch.
    pub last_used: i64,
}

impl Store {
    /// Record a new session under its cookie's `digest`, and forget those idle since before
    /// `expired` (ms).
    pub async fn open_session(
        &self,
        digest: &str,
        record: &SessionRecord,
        expired: i64,
    ) -> Result<(), StoreError> {
        sqlx::query("DELETE FROM web_sessions WHERE last_used < $1")
            .bind(expired)
            .execute(&self.pool)
            .await?;
        sqlx::query(
            "INSERT INTO web_sessions (digest, key_digest, account, user_name, csrf, last_used) VALUES ($1, $2, $3, $4, $5, $6)",
        )
        .bind(digest)
        .bind(record.key_digest.clone())
        .bind(record.user.as_ref().map(|(account, _)| account.clone()))
        .bind(record.user.as_ref().map(|(_, name)| name.clone()))
        .bind(&record.csrf)
        .bind(record.last_used)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// The session recorded under `digest`.
    pub async fn session(&self, digest: &str) -> Result<Option<SessionRecord>, StoreError> {
        let row = sqlx::query(
            "SELECT key_digest, account, user_name, csrf, last_used FROM web_sessions WHERE digest = $1",
        )
        .bind(digest)
        .fetch_optional(&self.pool)
        .await?;
        row.map(|r| -> Result<SessionRecord, sqlx::Error> {
            Ok(SessionRecord {
                key_digest: r.try_get("key_digest")?,
                user: r
                    .try_get::<Option<String>, _>("account")?
                    .zip(r.try_get::<Option<String>, _>("user_name")?),
                csrf: r.try_get("csrf")?,
                last_used: r.try_get("last_used")?,
            })
        })
        .transpose()
        .map_err(StoreError::from)
    }

    /// The session was used at `at` (ms).
    pub async fn touch_session(&self, digest: &str, at: i64) -> Result<(), StoreError> {
        sqlx::query("UPDATE web_sessions SET last_used = $1 WHERE digest = $2")
            .bind(at)
            .bind(digest)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// The session ended (signed out, or its user or key no longer counts). The auth epoch
    /// rises, so that every process checks its sessions again and drops this one too.
    pub async fn close_session(&self, digest: &str) -> Result<(), StoreError> {
        let closed = sqlx::query("DELETE FROM web_sessions WHERE digest = $1")
            .bind(digest)
            .execute(&self.pool)
            .await?;
        if closed.rows_affected() > 0 {
            self.raise_auth_epoch().await?;
        }
        Ok(())
    }
}
