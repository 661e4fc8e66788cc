//! Accounts: who may see the lifts of one domain, with the API key each was made with.

use sqlx::Row;

use cloud_types::now_ms;

use crate::secrets::{digest, secret};
use crate::{Store, StoreError};

impl Store {
    /// Create an account for `domain`; returns its API key (shown once, stored as a digest).
    pub async fn add_account(&self, name: &str, domain: &str) -> Result<String, StoreError> {
        let key = secret("clk_");
        sqlx::query(
            "INSERT INTO accounts (name, domain, key_hash, created) VALUES ($1, $2, $3, $4)",
        )
        .bind(name)
        .bind(domain)
        .bind(digest(&key))
        .bind(now_ms())
        .execute(&self.pool)
        .await?;
        Ok(key)
    }

    /// Whether an account owns `domain`.
    pub async fn domain_exists(&self, domain: &str) -> Result<bool, StoreError> {
        let row = sqlx::query("SELECT COUNT(*) AS n FROM accounts WHERE domain = $1")
            .bind(domain)
            .fetch_one(&self.pool)
            .await?;
        Ok(row.try_get::<i64, _>("n")? > 0)
    }
}
