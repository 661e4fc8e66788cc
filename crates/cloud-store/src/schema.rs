//! The tables (`SCHEMA`) and the changes to them since (`MIGRATIONS`), applied when a store
//! opens.

use sqlx::{AnyConnection, AnyPool, Connection, Executor, Row};

use crate::StoreError;
use cloud_types::now_ms;

/// The key of the PostgreSQL advisory lock under which a process creates and migrates the
/// schema: processes starting together take turns (CREATE … IF NOT EXISTS is not safe against
/// a concurrent creation of the same table: two of three processes started at once died of
/// `duplicate key value violates unique constraint "pg_type_typname_nsp_index"`).
const SCHEMA_LOCK: i64 = 0x6361_6e6c_6966_7401;

/// Create the tables and apply the migrations not yet applied, on one connection: on
/// PostgreSQL under an advisory lock, with notices silenced (each start had logged a
/// `relation "…" already exists, skipping` per table).
pub(crate) async fn create(pool: &AnyPool, sqlite: bool) -> Result<(), StoreError> {
    let mut conn = pool.acquire().await?;
    if !sqlite {
        conn.execute("SET client_min_messages = warning").await?;
        sqlx::query("SELECT pg_advisory_lock($1)")
            .bind(SCHEMA_LOCK)
            .execute(&mut *conn)
            .await?;
    }
    let created = create_on(&mut conn).await;
    if !sqlite {
        let unlocked = sqlx::query("SELECT pg_advisory_unlock($1)")
            .bind(SCHEMA_LOCK)
            .execute(&mut *conn)
            .await;
        let reset = conn.execute("RESET client_min_messages").await;
        if created.is_err() || unlocked.is_err() || reset.is_err() {
            // Not back into the pool with a lock or a setting of its own.
            let _ = conn.detach().close().await;
        }
    }
    created?;
    Ok(())
}

async fn create_on(conn: &mut AnyConnection) -> Result<(), StoreError> {
    for statement in SCHEMA {
        conn.execute(*statement).await?;
    }
    migrate(conn).await
}

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
    "CREATE TABLE IF NOT EXISTS users (name TEXT NOT NULL, account TEXT NOT NULL, role TEXT NOT NULL, secret_hash TEXT NOT NULL, disabled BIGINT, created BIGINT NOT NULL, PRIMARY KEY (account, name))",
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
    // Roll-ups of pushed values per object, minute and hour (docs/PORTAL.md §History): what a
    // chart of a day or a week reads instead of millions of raw rows.
    "CREATE TABLE IF NOT EXISTS telemetry_minute (lift TEXT NOT NULL, mplex TEXT NOT NULL, at BIGINT NOT NULL, min DOUBLE PRECISION, max DOUBLE PRECISION, last TEXT NOT NULL, last_at BIGINT NOT NULL, count BIGINT NOT NULL, PRIMARY KEY (lift, mplex, at))",
    "CREATE INDEX IF NOT EXISTS telemetry_minute_by_time ON telemetry_minute (at)",
    "CREATE TABLE IF NOT EXISTS telemetry_hour (lift TEXT NOT NULL, mplex TEXT NOT NULL, at BIGINT NOT NULL, min DOUBLE PRECISION, max DOUBLE PRECISION, last TEXT NOT NULL, last_at BIGINT NOT NULL, count BIGINT NOT NULL, PRIMARY KEY (lift, mplex, at))",
    "CREATE INDEX IF NOT EXISTS telemetry_hour_by_time ON telemetry_hour (at)",
    // Until when every minute is rolled up (one row).
    "CREATE TABLE IF NOT EXISTS rollup_state (id BIGINT PRIMARY KEY, done BIGINT NOT NULL)",
    // Outcomes of writes made with an Idempotency-Key, by whose credential and key.
    "CREATE TABLE IF NOT EXISTS idempotency (scope TEXT NOT NULL, key TEXT NOT NULL, fingerprint TEXT NOT NULL, status BIGINT, body TEXT, created BIGINT NOT NULL, PRIMARY KEY (scope, key))",
    "CREATE INDEX IF NOT EXISTS idempotency_by_time ON idempotency (created)",
    // One row a process writes now and then: whether the database takes writes.
    "CREATE TABLE IF NOT EXISTS write_probe (id BIGINT PRIMARY KEY, at BIGINT NOT NULL)",
    // Users' subscriptions, registered again by whichever process the lift's gateway connects to.
    "CREATE TABLE IF NOT EXISTS subscriptions (lift TEXT NOT NULL, user_name TEXT NOT NULL, mplex TEXT NOT NULL, inhibit BIGINT NOT NULL, threshold DOUBLE PRECISION NOT NULL, PRIMARY KEY (lift, user_name, mplex))",
    // Each change of a lift's status (in service, out of service, offline, unknown): what the
    // availability reports integrate.
    "CREATE TABLE IF NOT EXISTS lift_status (lift TEXT NOT NULL, at BIGINT NOT NULL, status TEXT NOT NULL)",
    "CREATE INDEX IF NOT EXISTS lift_status_by_lift ON lift_status (lift, at)",
];

/// Changes to tables of an existing database, each applied once, in order, its statements in
/// one transaction (a database created before a change gets it when the portal next starts; a
/// new one gets them all at once).
const MIGRATIONS: &[(i64, &[&str])] = &[
    // Token lifecycle: when the token in use was confirmed, and the one a rotation sent.
    (1, &["ALTER TABLE gateways ADD COLUMN token_set BIGINT NOT NULL DEFAULT 0"]),
    (2, &["ALTER TABLE gateways ADD COLUMN token_next TEXT"]),
    // One active alarm per condition, also when several processes of a cluster raise it at
    // once: duplicates an older portal may have left are cleared first.
    (3, &["UPDATE alarms SET cleared = raised WHERE cleared IS NULL AND id NOT IN \
         (SELECT MIN(id) FROM alarms WHERE cleared IS NULL GROUP BY lift, kind, net, node, code)"]),
    (4, &["CREATE UNIQUE INDEX IF NOT EXISTS alarms_one_active ON alarms (lift, kind, net, node, code) WHERE cleared IS NULL"]),
    // Audit first: an entry is written as intended before the lift is asked, and completed
    // with its outcome by its id.
    (5, &["ALTER TABLE audit ADD COLUMN id BIGINT"]),
    (6, &["CREATE INDEX IF NOT EXISTS audit_by_id ON audit (id)"]),
    // Refused CONNECTs: a digest of the token offered (never the token), pruned by age.
    (7, &["ALTER TABLE refused ADD COLUMN token_digest TEXT"]),
    (8, &["CREATE INDEX IF NOT EXISTS refused_by_time ON refused (at)"]),
    (9, &["CREATE INDEX IF NOT EXISTS audit_by_time ON audit (at)"]),
    // Lifts belong to accounts: an audit entry belongs to the account of its lift when it was
    // written (a retired lift's key may later be another account's).
    (10, &["ALTER TABLE audit ADD COLUMN owner TEXT"]),
    (11, &["UPDATE audit SET owner = (SELECT a.name FROM gateways g JOIN accounts a ON a.domain = g.domain WHERE g.id = audit.lift) WHERE owner IS NULL"]),
    (12, &["CREATE INDEX IF NOT EXISTS audit_by_owner ON audit (owner, at)"]),
    // Users belong to accounts: a name is unique within its account (another account's
    // administrator learns nothing of it); keys and sessions name the account of their user.
    (13, &["ALTER TABLE api_keys ADD COLUMN account TEXT"]),
    (
        14,
        &["UPDATE api_keys SET account = (SELECT u.account FROM users u WHERE u.name = api_keys.user_name) WHERE account IS NULL"],
    ),
    (15, &["ALTER TABLE web_sessions ADD COLUMN account TEXT"]),
    (
        16,
        &["UPDATE web_sessions SET account = (SELECT u.account FROM users u WHERE u.name = web_sessions.user_name) WHERE account IS NULL AND user_name IS NOT NULL"],
    ),
    (
        17,
        &[
            "CREATE TABLE users_by_account (name TEXT NOT NULL, account TEXT NOT NULL, role TEXT NOT NULL, secret_hash TEXT NOT NULL, disabled BIGINT, created BIGINT NOT NULL, PRIMARY KEY (account, name))",
            "INSERT INTO users_by_account (name, account, role, secret_hash, disabled, created) SELECT name, account, role, secret_hash, disabled, created FROM users",
            "DROP TABLE users",
            "ALTER TABLE users_by_account RENAME TO users",
        ],
    ),
    // Where an audited request came from.
    (18, &["ALTER TABLE audit ADD COLUMN address TEXT"]),
    // Users of single sign-on, by their provider's issuer and subject.
    (
        19,
        &[
            "ALTER TABLE users ADD COLUMN sso_subject TEXT",
            "CREATE UNIQUE INDEX IF NOT EXISTS users_by_sso ON users (account, sso_subject)",
        ],
    ),
    // The availability an account promises its customers (the monthly report's target).
    (20, &["ALTER TABLE accounts ADD COLUMN availability_target DOUBLE PRECISION"]),
];

/// Apply the [`MIGRATIONS`] not yet recorded, each with its record in one transaction (under
/// the schema lock on PostgreSQL, so that processes starting together apply each once).
async fn migrate(conn: &mut AnyConnection) -> Result<(), StoreError> {
    for (version, statements) in MIGRATIONS {
        let mut tx = conn.begin().await?;
        let applied = sqlx::query("SELECT COUNT(*) AS n FROM schema_migrations WHERE version = $1")
            .bind(version)
            .fetch_one(&mut *tx)
            .await?
            .try_get::<i64, _>("n")?;
        if applied == 0 {
            for statement in *statements {
                sqlx::query(statement).execute(&mut *tx).await?;
            }
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
