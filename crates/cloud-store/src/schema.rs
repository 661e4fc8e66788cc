//! The tables (`SCHEMA`) and the changes to them since (`MIGRATIONS`), applied when a store
//! opens.

use sqlx::{AnyPool, Row};

use crate::StoreError;
use cloud_types::now_ms;

/// The tables and indexes of a new database (each statement leaves an existing one alone).
pub(crate) const SCHEMA: &[&str] = &[
    "CREATE TABLE IF NOT EXISTS accounts (name TEXT PRIMARY KEY, domain TEXT NOT NULL UNIQUE, key_hash TEXT NOT NULL UNIQUE, created BIGINT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS gateways (id TEXT PRIMARY KEY, vendorid BIGINT NOT NULL, productcode BIGINT NOT NULL, sernum TEXT NOT NULL, liftnum TEXT NOT NULL, hardware TEXT NOT NULL, software TEXT NOT NULL, boardhash TEXT NOT NULL, domain TEXT NOT NULL, api BIGINT NOT NULL, token_hash TEXT, last_seen BIGINT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS refused (at BIGINT NOT NULL, lift TEXT NOT NULL, peer TEXT NOT NULL, cause TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS telemetry (lift TEXT NOT NULL, mplex TEXT NOT NULL, node BIGINT NOT NULL, value TEXT NOT NULL, at BIGINT NOT NULL)",
    "CREATE INDEX IF NOT EXISTS telemetry_by_object ON telemetry (lift, mplex, at)",
    "CREATE INDEX IF NOT EXISTS telemetry_by_time ON telemetry (at)",
    "CREATE TABLE IF NOT EXISTS audit (at BIGINT NOT NULL, account TEXT NOT NULL, lift TEXT NOT NULL, action TEXT NOT NULL, object TEXT NOT NULL, old_value TEXT, new_value TEXT NOT NULL, result TEXT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS events (lift TEXT NOT NULL, at BIGINT NOT NULL, kind TEXT NOT NULL, body TEXT NOT NULL)",
    "CREATE INDEX IF NOT EXISTS events_by_lift ON events (lift, at)",
    "CREATE INDEX IF NOT EXISTS events_by_time ON events (at)",
    "CREATE TABLE IF NOT EXISTS alarms (id BIGINT PRIMARY KEY, lift TEXT NOT NULL, kind TEXT NOT NULL, net BIGINT NOT NULL, node BIGINT NOT NULL, code TEXT NOT NULL, severity TEXT NOT NULL, text TEXT NOT NULL, raised BIGINT NOT NULL, ack_by TEXT, ack_at BIGINT, ack_comment TEXT, cleared BIGINT)",
    "CREATE INDEX IF NOT EXISTS alarms_by_lift ON alarms (lift, raised)",
    "CREATE INDEX IF NOT EXISTS alarms_active ON alarms (cleared)",
    "CREATE TABLE IF NOT EXISTS webhook_outbox (id BIGINT PRIMARY KEY, url TEXT NOT NULL, body TEXT NOT NULL, lift TEXT NOT NULL, created BIGINT NOT NULL, attempts BIGINT NOT NULL, next_at BIGINT NOT NULL, delivered BIGINT, given_up BIGINT, last_error TEXT)",
    "CREATE INDEX IF NOT EXISTS webhook_outbox_due ON webhook_outbox (delivered, given_up, next_at)",
    "CREATE TABLE IF NOT EXISTS schema_migrations (version BIGINT PRIMARY KEY, applied BIGINT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS users (name TEXT PRIMARY KEY, account TEXT NOT NULL, role TEXT NOT NULL, secret_hash TEXT NOT NULL, disabled BIGINT, created BIGINT NOT NULL)",
    "CREATE TABLE IF NOT EXISTS api_keys (id TEXT PRIMARY KEY, key_hash TEXT NOT NULL UNIQUE, user_name TEXT NOT NULL, created BIGINT NOT NULL, expires BIGINT, revoked BIGINT)",
    "CREATE TABLE IF NOT EXISTS auth_epoch (id BIGINT PRIMARY KEY, epoch BIGINT NOT NULL)",
    "INSERT INTO auth_epoch (id, epoch) SELECT 1, 0 WHERE NOT EXISTS (SELECT 1 FROM auth_epoch WHERE id = 1)",
    // Who elevated which lift's connection (crate::elevation), for every process of a cluster.
    "CREATE TABLE IF NOT EXISTS elevations (lift TEXT PRIMARY KEY, user_name TEXT NOT NULL, privilege BIGINT NOT NULL, until BIGINT NOT NULL, connection BIGINT NOT NULL)",
    // Browser sessions, by the SHA-256 digest of their cookie: any process of a cluster (or
    // the portal after a restart) knows them.
    "CREATE TABLE IF NOT EXISTS web_sessions (digest TEXT PRIMARY KEY, key_digest TEXT, user_name TEXT, csrf TEXT NOT NULL, last_used BIGINT NOT NULL)",
    // A cluster's TLS session-ticket keys (one row): every process resumes every session.
    "CREATE TABLE IF NOT EXISTS tls_ticket_keys (id BIGINT PRIMARY KEY, keys TEXT NOT NULL, version BIGINT NOT NULL)",
    // Users' subscriptions, registered again by whichever process the lift's gateway connects to.
    "CREATE TABLE IF NOT EXISTS subscriptions (lift TEXT NOT NULL, user_name TEXT NOT NULL, mplex TEXT NOT NULL, inhibit BIGINT NOT NULL, threshold DOUBLE PRECISION NOT NULL, PRIMARY KEY (lift, user_name, mplex))",
];

/// Changes to tables of an existing database, each applied once, in order (a database created
/// before a change gets it when the portal next starts; a new one gets them all at once).
const MIGRATIONS: &[(i64, &str)] = &[
    // Token lifecycle: when the token in use was confirmed, and the one a rotation sent.
    (
        1,
        "ALTER TABLE gateways ADD COLUMN token_set BIGINT NOT NULL DEFAULT 0",
    ),
    (2, "ALTER TABLE gateways ADD COLUMN token_next TEXT"),
    // One active alarm per condition, also when several processes of a cluster raise it at
    // once: duplicates an older portal may have left are cleared first.
    (
        3,
        "UPDATE alarms SET cleared = raised WHERE cleared IS NULL AND id NOT IN \
         (SELECT MIN(id) FROM alarms WHERE cleared IS NULL GROUP BY lift, kind, net, node, code)",
    ),
    (
        4,
        "CREATE UNIQUE INDEX IF NOT EXISTS alarms_one_active ON alarms (lift, kind, net, node, code) WHERE cleared IS NULL",
    ),
];

/// Apply the [`MIGRATIONS`] not yet recorded, each with its record in one transaction (on
/// PostgreSQL under a table lock, so that portal processes starting together apply each once).
pub(crate) async fn migrate(pool: &AnyPool, sqlite: bool) -> Result<(), StoreError> {
    for (version, statement) in MIGRATIONS {
        let mut tx = pool.begin().await?;
        if !sqlite {
            sqlx::query("LOCK TABLE schema_migrations IN EXCLUSIVE MODE")
                .execute(&mut *tx)
                .await?;
        }
        let applied = sqlx::query("SELECT COUNT(*) AS n FROM schema_migrations WHERE version = $1")
            .bind(version)
            .fetch_one(&mut *tx)
            .await?
            .try_get::<i64, _>("n")?;
        if applied == 0 {
            sqlx::query(statement).execute(&mut *tx).await?;
            sqlx::query("INSERT INTO schema_migrations (version, applied) VALUES ($1, $2)")
                .bind(version)
                .bind(now_ms())
                .execute(&mut *tx)
                .await?;
        }
        tx.commit().await?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Store;
    use sqlx::any::AnyPoolOptions;

    /// A database made before the token columns existed gets them, once.
    #[tokio::test]
    async fn an_older_database_is_migrated() {
        let dir = tempfile::tempdir().unwrap();
        let url = format!("sqlite://{}", dir.path().join("old.db").display());
        {
            sqlx::any::install_default_drivers();
            let pool = AnyPoolOptions::new()
                .connect(&format!("{url}?mode=rwc"))
                .await
                .unwrap();
            sqlx::query("CREATE TABLE gateways (id TEXT PRIMARY KEY, vendorid BIGINT NOT NULL, productcode BIGINT NOT NULL, sernum TEXT NOT NULL, liftnum TEXT NOT NULL, hardware TEXT NOT NULL, software TEXT NOT NULL, boardhash TEXT NOT NULL, domain TEXT NOT NULL, api BIGINT NOT NULL, token_hash TEXT, last_seen BIGINT NOT NULL)")
                .execute(&pool)
                .await
                .unwrap();
            sqlx::query("INSERT INTO gateways VALUES ('1050-4096-1', 1050, 4096, '1', '', '', '', 'B', 'MAS', 1, 'h', 0)")
                .execute(&pool)
                .await
                .unwrap();
            pool.close().await;
        }
        for _ in 0..2 {
            let store = Store::open(&url).await.unwrap();
            store.set_next_token("1050-4096-1", "N").await.unwrap();
            let n: i64 = sqlx::query("SELECT COUNT(*) AS n FROM schema_migrations")
                .fetch_one(&store.pool)
                .await
                .unwrap()
                .get("n");
            assert_eq!(n, MIGRATIONS.len() as i64);
            store.pool.close().await;
        }
    }
}
