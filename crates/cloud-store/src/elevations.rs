//! Who elevated which lift's connection (NXg §6.4), for every process of a cluster.

use sqlx::Row;

use crate::{Store, StoreError};

/// A lift's elevation grant (the portal's `auth::elevation`): who elevated, to what, until when (ms since
/// the Unix epoch), on which connection (its epoch).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ElevationGrant {
    /// The user who entered the password.
    pub user: String,
    /// The privilege the gateway granted.
    pub privilege: u32,
    /// When it runs out (ms).
    pub until: i64,
    /// The connection it was granted on.
    pub connection: u64,
}

impl Store {
    /// The lift's grant, if one is recorded.
    pub async fn grant(&self, lift: &str) -> Result<Option<ElevationGrant>, StoreError> {
        let row = sqlx::query(
            "SELECT user_name, privilege, until, connection FROM elevations WHERE lift = $1",
        )
        .bind(lift)
        .fetch_optional(&self.pool)
        .await?;
        row.map(|r| -> Result<ElevationGrant, sqlx::Error> {
            let number = |column: &str| -> Result<i64, sqlx::Error> { r.try_get(column) };
            Ok(ElevationGrant {
                user: r.try_get("user_name")?,
                privilege: u32::try_from(number("privilege")?).unwrap_or(0),
                until: number("until")?,
                connection: u64::try_from(number("connection")?).unwrap_or(0),
            })
        })
        .transpose()
        .map_err(StoreError::from)
    }

    /// Record the lift's grant, replacing any other.
    pub async fn set_grant(&self, lift: &str, grant: &ElevationGrant) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO elevations (lift, user_name, privilege, until, connection) VALUES ($1, $2, $3, $4, $5) \
             ON CONFLICT (lift) DO UPDATE SET user_name = excluded.user_name, privilege = excluded.privilege, until = excluded.until, connection = excluded.connection",
        )
        .bind(lift)
        .bind(&grant.user)
        .bind(i64::from(grant.privilege))
        .bind(grant.until)
        .bind(i64::try_from(grant.connection).unwrap_or(i64::MAX))
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Forget the lift's grant.
    pub async fn drop_grant(&self, lift: &str) -> Result<(), StoreError> {
        sqlx::query("DELETE FROM elevations WHERE lift = $1")
            .bind(lift)
            .execute(&self.pool)
            .await?;
        Ok(())
    }
}
