//! Accounts: who may see the lifts of one domain, with the API key each was made with.

use sqlx::Row;

use cloud_types::now_ms;
use cloud_types::users::Account;

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

    /// The account named `name`.
    pub async fn account(&self, name: &str) -> Result<Option<Account>, StoreError> {
        let row = sqlx::query("SELECT name, domain FROM accounts WHERE name = $1")
            .bind(name)
            .fetch_optional(&self.pool)
            .await?;
        row.map(|r| -> Result<Account, sqlx::Error> {
            Ok(Account {
                name: r.try_get("name")?,
                domain: r.try_get("domain")?,
            })
        })
        .transpose()
        .map_err(StoreError::from)
    }

    /// The accounts whose domain token is shorter than `length` characters (a guess away
    /// The availability account `name` promises (0–1), if it set one.
    pub async fn availability_target(&self, name: &str) -> Result<Option<f64>, StoreError> {
        let row = sqlx::query("SELECT availability_target FROM accounts WHERE name = $1")
            .bind(name)
            .fetch_optional(&self.pool)
            .await?;
        Ok(match row {
            Some(r) => r.try_get("availability_target")?,
            None => None,
        })
    }

    /// Account `name` promises `target` (0–1; none: the portal's default).
    pub async fn set_availability_target(
        &self,
        name: &str,
        target: Option<f64>,
    ) -> Result<(), StoreError> {
        sqlx::query("UPDATE accounts SET availability_target = $1 WHERE name = $2")
            .bind(target)
            .bind(name)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// from admitting lifts into them).
    pub async fn short_domains(&self, length: usize) -> Result<Vec<String>, StoreError> {
        let rows = sqlx::query("SELECT name, domain FROM accounts ORDER BY name")
            .fetch_all(&self.pool)
            .await?;
        let mut short = Vec::new();
        for r in rows {
            if r.try_get::<String, _>("domain")?.chars().count() < length {
                short.push(r.try_get("name")?);
            }
        }
        Ok(short)
    }

    /// The accounts with a lift of id `id`, each with the lift's key (docs/PORTAL.md §Lifts and
    /// accounts): for an administrator who names a lift without its account.
    pub async fn owners_of(&self, id: &str) -> Result<Vec<(Account, String)>, StoreError> {
        let rows = sqlx::query(
            "SELECT a.name, a.domain, g.id FROM gateways g JOIN accounts a ON a.domain = g.domain \
             WHERE g.id = $1 OR g.id = $2 || a.name ORDER BY a.name",
        )
        .bind(id)
        .bind(cloud_types::lifts::scoped_key(id, ""))
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok((
                    Account {
                        name: r.try_get("name")?,
                        domain: r.try_get("domain")?,
                    },
                    r.try_get("id")?,
                ))
            })
            .collect::<Result<_, sqlx::Error>>()
            .map_err(StoreError::from)
    }
}
