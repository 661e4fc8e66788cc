//! Backups of a SQLite portal (docs/PORTAL.md §Backups): a consistent copy taken while the
//! portal runs (`VACUUM INTO`: SQLite's online copy in one read transaction, so every write
//! committed before it starts is in it and none after), and the checks a copy passes before it
//! is put back. A PostgreSQL portal is backed up with `pg_dump`.

use std::path::Path;

use sqlx::{Connection, Row};

use crate::{Store, StoreError};

/// What a backup holds, as checked.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Contents {
    /// Lifts in its registry.
    pub lifts: i64,
    /// Pushed values.
    pub values: i64,
    /// Schema changes it has (the portal that wrote it).
    pub migrations: i64,
}

/// Why a backup was not taken or is not fit to be put back.
#[derive(Debug, thiserror::Error)]
pub enum BackupError {
    /// The database is PostgreSQL's.
    #[error("a PostgreSQL portal is backed up with pg_dump (docs/PORTAL.md §Backups)")]
    Postgres,
    /// The file is not a portal's database.
    #[error("{0}")]
    NotAPortal(String),
    /// The database.
    #[error(transparent)]
    Store(#[from] StoreError),
}

impl From<sqlx::Error> for BackupError {
    fn from(e: sqlx::Error) -> Self {
        BackupError::Store(StoreError::from(e))
    }
}

impl Store {
    /// Write a consistent copy of this SQLite database to `file` (which must not exist) while
    /// the portal goes on writing.
    pub async fn backup_to(&self, file: &Path) -> Result<(), BackupError> {
        if self.copy.is_some() {
            return Err(BackupError::Postgres);
        }
        sqlx::query("VACUUM INTO $1")
            .bind(file.to_string_lossy().into_owned())
            .execute(&self.pool)
            .await?;
        Ok(())
    }
}

/// Check that `file` is a whole portal database (SQLite's integrity check, the portal's
/// tables) without changing it; what it holds.
pub async fn check(file: &Path) -> Result<Contents, BackupError> {
    sqlx::any::install_default_drivers();
    let url = format!("sqlite://{}?mode=ro", file.display());
    let mut conn = sqlx::AnyConnection::connect(&url).await?;
    let integrity: String = sqlx::query("PRAGMA integrity_check")
        .fetch_one(&mut conn)
        .await?
        .try_get(0)?;
    if integrity != "ok" {
        return Err(BackupError::NotAPortal(format!(
            "{}: SQLite's integrity check says {integrity}",
            file.display()
        )));
    }
    let migrations = count(&mut conn, "schema_migrations").await.map_err(|_| {
        BackupError::NotAPortal(format!("{}: no canlift portal database", file.display()))
    })?;
    let lifts = count(&mut conn, "gateways").await?;
    let values = count(&mut conn, "telemetry").await?;
    Ok(Contents {
        lifts,
        values,
        migrations,
    })
}

async fn count(conn: &mut sqlx::AnyConnection, table: &str) -> Result<i64, sqlx::Error> {
    sqlx::query(&format!("SELECT COUNT(*) AS n FROM {table}"))
        .fetch_one(conn)
        .await?
        .try_get("n")
}
