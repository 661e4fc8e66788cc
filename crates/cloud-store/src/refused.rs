//! Refused connection attempts: which lift, from where, why — and of a token offered only its
//! digest. Bounded by age and by count ([`Store::forget_refused`]): a sender's CONNECTs must not
//! fill the disk.

use sqlx::Row;

use cloud_types::now_ms;

use crate::{Store, StoreError};

/// One refused CONNECT.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Refusal {
    /// When (ms since the epoch).
    pub at: i64,
    /// The lift it claimed to be.
    pub lift: String,
    /// Where it came from.
    pub peer: String,
    /// Why it was refused (the portal's words, never the sender's text).
    pub cause: String,
    /// The SHA-256 digest of the domain token it gave (never the token).
    pub token_digest: Option<String>,
}

impl Store {
    /// Record a refused connection attempt.
    pub async fn refused(&self, refusal: &Refusal) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO refused (at, lift, peer, cause, token_digest) VALUES ($1, $2, $3, $4, $5)",
        )
        .bind(refusal.at)
        .bind(&refusal.lift)
        .bind(&refusal.peer)
        .bind(&refusal.cause)
        .bind(&refusal.token_digest)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Refused attempts for a lift, newest first.
    pub async fn refusals(&self, lift: &str) -> Result<Vec<Refusal>, StoreError> {
        let rows = sqlx::query(
            "SELECT at, lift, peer, cause, token_digest FROM refused WHERE lift = $1 ORDER BY at DESC",
        )
        .bind(lift)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(Refusal {
                    at: r.try_get("at")?,
                    lift: r.try_get("lift")?,
                    peer: r.try_get("peer")?,
                    cause: r.try_get("cause")?,
                    token_digest: r.try_get("token_digest")?,
                })
            })
            .collect()
    }

    /// Delete refused attempts older than `before` (ms), and all but the newest `keep`; how
    /// many went.
    pub async fn forget_refused(&self, before: i64, keep: u32) -> Result<u64, StoreError> {
        let old = sqlx::query("DELETE FROM refused WHERE at < $1")
            .bind(before)
            .execute(&self.pool)
            .await?
            .rows_affected();
        let cut: Option<i64> =
            sqlx::query("SELECT at FROM refused ORDER BY at DESC LIMIT 1 OFFSET $1")
                .bind(i64::from(keep))
                .fetch_optional(&self.pool)
                .await?
                .map(|r| r.try_get("at"))
                .transpose()?;
        let beyond = match cut {
            Some(at) => sqlx::query("DELETE FROM refused WHERE at <= $1")
                .bind(at)
                .execute(&self.pool)
                .await?
                .rows_affected(),
            None => 0,
        };
        Ok(old + beyond)
    }
}

/// A refusal now.
impl Refusal {
    /// `lift` refused now from `peer` for `cause`, having offered domain token `domain`.
    pub fn now(lift: &str, peer: &str, cause: &str, domain: &str) -> Refusal {
        Refusal {
            at: now_ms(),
            lift: lift.to_owned(),
            peer: peer.to_owned(),
            cause: cause.to_owned(),
            token_digest: (!domain.is_empty()).then(|| crate::digest(domain)),
        }
    }
}
