//! What the portal keeps: accounts with their API keys, the gateway registry with token hashes,
//! refused connection attempts, telemetry (pushed values), the audit log, and bus events,
//! alarms and undelivered webhook notifications (see `alarms.rs`), in SQLite or PostgreSQL through
//! sqlx (one set of portable statements with `$n` parameters).
//!
//! Secrets are stored only as SHA-256 digests (API keys, cloud tokens); tokens are compared with
//! the one on record in time independent of where they differ.

mod alarms;
mod subscriptions;
mod ticket_keys;
mod users;

pub use alarms::{new_id, AlarmFilter, EventRow, OutboxEntry};
pub use subscriptions::StoredSubscription;
pub use users::{ElevationGrant, SessionRecord, UserError};

use std::collections::HashMap;

use cloud_types::audit::AuditEntry;
use cloud_types::lifts::{lift_id, LiftRecord};
use cloud_types::now_ms;
use cloud_types::users::Operator;

use nxg::msg::{Connect, Identity};
use rand::RngCore;
use sqlx::any::{AnyPoolOptions, AnyRow};
use sqlx::postgres::PgPoolCopyExt;
use sqlx::{AnyPool, ConnectOptions, Connection, Executor, Row};

/// A pooled PostgreSQL connection idle this long is pinged before it is used
/// ([`Store::open_pooled`]).
const PING_IDLE: std::time::Duration = std::time::Duration::from_secs(1);

/// A statement slower than this is worth a warning ([`timed`]).
const SLOW: std::time::Duration = std::time::Duration::from_secs(1);

/// `statement` (`rows` rows of `what`), with one short warning when it took longer than a second.
/// sqlx's own warning about slow statements is turned down to debug ([`quiet`]): it
/// carries the statement's whole text, kilobytes for a batch, once per batch while the database
/// is slow.
pub(crate) async fn timed<T>(
    what: &'static str,
    rows: usize,
    statement: impl std::future::Future<Output = T>,
) -> T {
    let started = std::time::Instant::now();
    let done = statement.await;
    let took = started.elapsed();
    if took >= SLOW {
        tracing::warn!(
            what,
            rows,
            took_ms = took.as_millis() as u64,
            "slow database statement"
        );
    }
    done
}

/// `options` with sqlx's slow-statement warning turned down to debug ([`timed`] says it short).
fn quiet<O: ConnectOptions>(options: O) -> O {
    options.log_slow_statements(log::LevelFilter::Debug, SLOW)
}

/// A database failure; cloned for everyone whose statement was in a batch that failed.
#[derive(Debug, Clone, thiserror::Error)]
#[error("database: {0}")]
pub struct StoreError(std::sync::Arc<sqlx::Error>);

impl From<sqlx::Error> for StoreError {
    fn from(e: sqlx::Error) -> StoreError {
        StoreError(std::sync::Arc::new(e))
    }
}

impl StoreError {
    /// Whether the database could not be reached (down, restarting, no connection free in
    /// time) rather than refusing the statement: worth trying again later.
    pub fn is_unavailable(&self) -> bool {
        matches!(
            *self.0,
            sqlx::Error::Io(_)
                | sqlx::Error::Tls(_)
                | sqlx::Error::PoolTimedOut
                | sqlx::Error::PoolClosed
                | sqlx::Error::WorkerCrashed
                | sqlx::Error::Protocol(_)
        ) || matches!(&*self.0, sqlx::Error::Database(e) if e.code().is_some_and(|c| {
            // PostgreSQL: admin shutdown, crash shutdown, cannot connect now.
            matches!(c.as_ref(), "57P01" | "57P02" | "57P03")
        }))
    }
}

/// How long an API key's account is taken from memory before the database is asked again, and
/// how long a remembered key still counts while the database cannot be reached
/// (docs/SECURITY.md §Bounds).
const KEY_FRESH: std::time::Duration = std::time::Duration::from_secs(60);
const KEY_KEPT: std::time::Duration = std::time::Duration::from_secs(3600);
/// Keys remembered at most (a full memory starts over).
const KEY_CACHE_ENTRIES: usize = 10_000;

/// Operators of API keys recently looked up, by the key's digest.
#[derive(Default)]
struct KeyCache(std::sync::Mutex<HashMap<String, (Operator, std::time::Instant)>>);

impl KeyCache {
    /// The operator of `digest` if it was looked up less than `age` ago.
    fn get(&self, digest: &str, age: std::time::Duration) -> Option<Operator> {
        let keys = self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        keys.get(digest)
            .filter(|(_, at)| at.elapsed() < age)
            .map(|(account, _)| account.clone())
    }

    fn put(&self, digest: String, operator: Operator) {
        let mut keys = self
            .0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if keys.len() >= KEY_CACHE_ENTRIES {
            keys.clear();
        }
        keys.insert(digest, (operator, std::time::Instant::now()));
    }

    /// Forget every key (rights were taken away somewhere).
    fn clear(&self) {
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clear();
    }
}

/// SHA-256 hex of `secret`.
pub fn digest(secret: &str) -> String {
    hex::encode(ring::digest::digest(
        &ring::digest::SHA256,
        secret.as_bytes(),
    ))
}

/// The NXg password hash (NXg §6.4): the unsalted SHA-1 of `password` as upper-case hex, as
/// `elevate_privilege` carries it and the gateway's `[privileges]` keeps it. Only ever sent to
/// the gateway, never stored by the portal.
pub fn passhash(password: &str) -> String {
    let sha1 = ring::digest::digest(&ring::digest::SHA1_FOR_LEGACY_USE_ONLY, password.as_bytes());
    hex::encode_upper(sha1)
}

/// A random secret of 128 bits as 32 hex digits, with a prefix.
pub fn secret(prefix: &str) -> String {
    let mut bytes = [0u8; 16];
    rand::rng().fill_bytes(&mut bytes);
    format!("{prefix}{}", hex::encode(bytes))
}

/// Apply the [`MIGRATIONS`] not yet recorded, each with its record in one transaction (on
/// PostgreSQL under a table lock, so that portal processes starting together apply each once).
async fn migrate(pool: &AnyPool, sqlite: bool) -> Result<(), StoreError> {
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

/// One pushed value to keep: which lift, object and node, the value, when it came.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TelemetryRow {
    /// Lift id.
    pub lift: String,
    /// The object (the gateway's spelling, `0x652001`).
    pub mplex: String,
    /// Node-ID the value is from (0: the lift controller).
    pub node: u8,
    /// The value in text form.
    pub value: String,
    /// When it arrived (ms since the epoch).
    pub at: i64,
}

/// What the registry keeps of a gateway's connections ([`Store::record`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum GatewayRecord {
    /// A gateway was admitted (CONNACK) at `at` (ms since the epoch), saying it is `identity`
    /// (NXg §5.2.1) of `domain` and speaking `api`: its row is made or its identity refreshed.
    Connected {
        /// As CONNECT said.
        identity: Identity,
        /// The domain token it gave.
        domain: String,
        /// The api version agreed.
        api: u32,
        /// When.
        at: i64,
    },
    /// A gateway was last heard at `at`: its connection ended.
    Seen {
        /// Lift id.
        lift: String,
        /// When.
        at: i64,
    },
    /// A gateway confirmed a token at `at` (NXg §5.4): only its digest is kept, with the time
    /// (for `[gateways] token_rotate_days`); a rotation in progress is over.
    Token {
        /// Lift id.
        lift: String,
        /// The token's digest.
        digest: String,
        /// When.
        at: i64,
    },
}

impl GatewayRecord {
    /// A gateway admitted now after `connect`, speaking `api`.
    pub fn connected(connect: &Connect, api: u32) -> GatewayRecord {
        GatewayRecord::Connected {
            identity: connect.identity.clone(),
            domain: connect.domaintoken.clone(),
            api,
            at: now_ms(),
        }
    }

    /// `lift`'s connection ended now.
    pub fn seen(lift: &str) -> GatewayRecord {
        GatewayRecord::Seen {
            lift: lift.to_owned(),
            at: now_ms(),
        }
    }

    /// The lift the record is of.
    pub fn lift(&self) -> String {
        match self {
            GatewayRecord::Connected { identity, .. } => lift_id(identity),
            GatewayRecord::Seen { lift, .. } | GatewayRecord::Token { lift, .. } => lift.clone(),
        }
    }

    /// `lift`'s gateway confirmed `token` now.
    pub fn token(lift: &str, token: &str) -> GatewayRecord {
        GatewayRecord::Token {
            lift: lift.to_owned(),
            digest: digest(token),
            at: now_ms(),
        }
    }
}

/// What the registry says about a CONNECT.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Admission {
    /// No token on record (never issued, or reset by an administrator): accept and issue one.
    FirstContact {
        /// Whether users hold subscriptions of the lift (after a token reset they may).
        subscribed: bool,
    },
    /// The token matches the one on record (or the one being rotated to, which now is).
    Known(Known),
    /// Refused, with the cause to record.
    Refused(String),
}

/// What the registry knows of a gateway whose token matched.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Known {
    /// The boardhash on record when the CONNECT's differs (the gateway's hardware changed, or
    /// its token was copied to another board).
    pub board_was: Option<String>,
    /// When the token in use was confirmed (ms since the epoch; 0 when not recorded).
    pub token_set: i64,
    /// Whether users hold subscriptions of the lift (to register when it connects).
    pub subscribed: bool,
}

/// The portal's database.
#[derive(Clone)]
pub struct Store {
    pool: AnyPool,
    /// PostgreSQL only: connections of its own driver for telemetry by binary `COPY`, which
    /// sqlx's database-neutral driver does not offer.
    copy: Option<sqlx::PgPool>,
    keys: std::sync::Arc<KeyCache>,
    /// The auth epoch this process has seen (see `users`); sessions older than it are checked
    /// again.
    epoch: std::sync::Arc<std::sync::atomic::AtomicI64>,
}

const SCHEMA: &[&str] = &[
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

/// Connections to PostgreSQL a store opens at most by default (`[database] connections`).
pub const POSTGRES_CONNECTIONS: u32 = 16;

impl Store {
    /// Open (and create) the database at `url`: `sqlite://PATH` (created if missing),
    /// `sqlite::memory:`, or `postgres://USER:PASSWORD@HOST/DB` (with
    /// [`POSTGRES_CONNECTIONS`]).
    pub async fn open(url: &str) -> Result<Store, StoreError> {
        Store::open_pooled(url, POSTGRES_CONNECTIONS).await
    }

    /// [`Store::open`] with at most `postgres` connections to PostgreSQL (at least 1; two
    /// more write telemetry).
    pub async fn open_pooled(url: &str, postgres: u32) -> Result<Store, StoreError> {
        sqlx::any::install_default_drivers();
        let sqlite = url.starts_with("sqlite:");
        let url = if sqlite && !url.contains(":memory:") && !url.contains('?') {
            format!("{url}?mode=rwc")
        } else {
            url.to_owned()
        };
        // SQLite allows one writer at a time; an in-memory database lives in one connection.
        let connections = match (sqlite, url.contains(":memory:")) {
            (_, true) => 1,
            (true, false) => 4,
            (false, _) => postgres.max(1),
        };
        let pool = AnyPoolOptions::new()
            .max_connections(connections)
            // sqlx would ping a pooled connection before each use (and pings it again when it
            // is given back): for PostgreSQL that finds one a restarted server dropped. Only
            // a connection idle for a while is worth the round trip: one in steady use finds
            // out at its next statement, and in a reconnect storm the pings were a third of
            // the round trips each admission waited for while it held a connection. A SQLite
            // file has nothing to lose (its ping is a round trip to the connection's thread,
            // 5 % of a gateway's CONNECT in a profile).
            .test_before_acquire(false)
            .before_acquire(move |conn, meta| {
                Box::pin(async move {
                    if !sqlite && meta.idle_for >= PING_IDLE {
                        conn.ping().await?;
                    }
                    Ok(true)
                })
            })
            // A request that needs the database while it is down fails in seconds, not after
            // sqlx's default of 30 s.
            .acquire_timeout(std::time::Duration::from_secs(5))
            // Waiting for a pooled connection is what a reconnect storm does (thousands of
            // admissions, a few connections): sqlx's warning after 2 s would write a line per
            // gateway. A wait that fails is logged by whoever waited.
            .acquire_slow_threshold(std::time::Duration::from_secs(5))
            .after_connect(move |conn, _| {
                Box::pin(async move {
                    if sqlite {
                        conn.execute("PRAGMA busy_timeout = 5000").await?;
                        // With WAL, NORMAL syncs at checkpoints rather than at every commit: a
                        // power cut may lose the last transactions, never the database.
                        conn.execute("PRAGMA synchronous = NORMAL").await?;
                        // A batch of telemetry touches pages all over the table's indexes:
                        // with SQLite's 2 MB cache it spills them to the WAL before the commit.
                        conn.execute("PRAGMA cache_size = -32768").await?;
                        conn.execute("PRAGMA temp_store = MEMORY").await?;
                        // Checkpoints copy each page once however often it changed since the
                        // last one: fewer of them, fewer copies of the same index pages (the
                        // WAL grows to about 32 MiB before it is copied back).
                        conn.execute("PRAGMA wal_autocheckpoint = 8192").await?;
                    }
                    Ok(())
                })
            })
            .connect_with(quiet(url.parse::<sqlx::any::AnyConnectOptions>()?))
            .await?;
        if sqlite && !url.contains(":memory:") {
            sqlx::query("PRAGMA journal_mode = WAL")
                .execute(&pool)
                .await?;
        }
        for statement in SCHEMA {
            sqlx::query(statement).execute(&pool).await?;
        }
        migrate(&pool, sqlite).await?;
        let copy = match sqlite {
            true => None,
            false => Some(
                sqlx::postgres::PgPoolOptions::new()
                    .max_connections(2)
                    .acquire_timeout(std::time::Duration::from_secs(5))
                    .connect_lazy_with(quiet(url.parse::<sqlx::postgres::PgConnectOptions>()?)),
            ),
        };
        Ok(Store {
            pool,
            copy,
            keys: std::sync::Arc::default(),
            epoch: std::sync::Arc::default(),
        })
    }

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

    /// The operator an API key acts for (found by the key's digest: an index lookup reveals
    /// nothing of a random 128-bit key): the account's administrator for the account's own key,
    /// a user with its role for a user's key.
    ///
    /// A key found is remembered for a minute, so requests do not each cost a query, and while
    /// the database is unreachable a key that was valid within the hour still counts: operators
    /// keep reading lifts, which needs no database, through an outage. What is remembered is
    /// forgotten when the auth epoch rises (a user disabled, a key revoked: see
    /// [`Store::follow_auth_epoch`]).
    pub async fn operator_by_key(&self, key: &str) -> Result<Option<Operator>, StoreError> {
        let digest = digest(key);
        if let Some(operator) = self.keys.get(&digest, KEY_FRESH) {
            return Ok(Some(operator));
        }
        let operator = match self.operator_of_key(&digest).await {
            Ok(operator) => operator,
            Err(e) if e.is_unavailable() => {
                return match self.keys.get(&digest, KEY_KEPT) {
                    Some(operator) => Ok(Some(operator)),
                    None => Err(e),
                };
            }
            Err(e) => return Err(e),
        };
        if let Some(operator) = &operator {
            self.keys.put(digest, operator.clone());
        }
        Ok(operator)
    }

    /// Check the auth epoch every `period` for as long as the store lives: when it rose, the
    /// keys remembered are forgotten and sessions are checked again (docs/PORTAL.md §Users and
    /// roles). Run by the portal.
    pub async fn follow_auth_epoch(self, period: std::time::Duration) {
        let mut ticks = tokio::time::interval(period);
        ticks.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            ticks.tick().await;
            match self.auth_epoch().await {
                Ok(epoch) => {
                    let seen = self.epoch.swap(epoch, std::sync::atomic::Ordering::SeqCst);
                    if seen != epoch {
                        self.keys.clear();
                    }
                }
                Err(e) => tracing::debug!(error = %e, "auth epoch not read"),
            }
        }
    }

    /// The auth epoch this process has seen.
    pub fn seen_auth_epoch(&self) -> i64 {
        self.epoch.load(std::sync::atomic::Ordering::SeqCst)
    }

    /// How many more client connections PostgreSQL takes now (`max_connections` less those
    /// kept for superusers and those open); `None` for SQLite.
    pub async fn free_connections(&self) -> Result<Option<i64>, StoreError> {
        if self.copy.is_none() {
            return Ok(None);
        }
        let row = sqlx::query(
            "SELECT current_setting('max_connections')::bigint \
             - current_setting('superuser_reserved_connections')::bigint \
             - (SELECT COUNT(*) FROM pg_stat_activity WHERE backend_type = 'client backend') AS free",
        )
        .fetch_one(&self.pool)
        .await?;
        Ok(Some(row.try_get::<i64, _>("free")?))
    }

    /// Whether an account owns `domain`.
    pub async fn domain_exists(&self, domain: &str) -> Result<bool, StoreError> {
        let row = sqlx::query("SELECT COUNT(*) AS n FROM accounts WHERE domain = $1")
            .bind(domain)
            .fetch_one(&self.pool)
            .await?;
        Ok(row.try_get::<i64, _>("n")? > 0)
    }

    /// Decide on a CONNECT (NXg §5.2, §5.4): the registry is keyed by vendor, product and
    /// serial number; the domain token names the account.
    pub async fn admit(&self, connect: &Connect) -> Result<Admission, StoreError> {
        let mut admissions = self.admit_many(&[connect]).await?;
        admissions
            .pop()
            .ok_or_else(|| sqlx::Error::RowNotFound.into())
    }

    /// [`Store::admit`] for many CONNECTs in one statement, the answers in their order: a
    /// reconnect storm's admissions take a pooled connection and a round trip per batch
    /// instead of per gateway (docs/PORTAL.md §Stores).
    pub async fn admit_many(&self, connects: &[&Connect]) -> Result<Vec<Admission>, StoreError> {
        let Some(last) = connects.len().checked_sub(1) else {
            return Ok(Vec::new());
        };
        // Batches padded to a power of two (repeating the last CONNECT) make a few distinct
        // statements, each prepared once per connection, not one per batch size.
        let rows = connects.len().next_power_of_two();
        let values = parameter_rows(rows, 3);
        // Per CONNECT: whether an account has its domain, the gateway's row (NULLs when there
        // is none) and whether users hold subscriptions of the lift (most hold none: then
        // they are not read at CONNACK).
        let sql = format!(
            "SELECT v.column1 AS i, \
             (SELECT COUNT(*) FROM accounts WHERE domain = v.column3) AS accounts, \
             (SELECT COUNT(*) FROM (SELECT 1 FROM subscriptions WHERE lift = v.column2 LIMIT 1) AS s) AS subscribed, \
             g.token_hash, g.token_next, g.token_set, g.domain, g.boardhash \
             FROM (VALUES {values}) AS v LEFT JOIN gateways AS g ON g.id = v.column2"
        );
        let mut query = sqlx::query(&sql);
        for i in 0..rows {
            let connect = connects[i.min(last)];
            query = query
                .bind(i.min(last) as i64)
                .bind(lift_id(&connect.identity))
                .bind(&connect.domaintoken);
        }
        let mut found: Vec<Option<AnyRow>> = (0..connects.len()).map(|_| None).collect();
        for row in query.fetch_all(&self.pool).await? {
            let i = usize::try_from(row.try_get::<i64, _>("i")?).unwrap_or(usize::MAX);
            if let Some(slot) = found.get_mut(i) {
                *slot = Some(row);
            }
        }
        let mut admissions = Vec::with_capacity(connects.len());
        for (connect, row) in connects.iter().zip(found) {
            let Some(row) = row else {
                return Err(sqlx::Error::RowNotFound.into());
            };
            admissions.push(self.decide(connect, &row).await?);
        }
        Ok(admissions)
    }

    /// The admission of `connect` given what the registry holds of it (a row of
    /// [`Store::admit_many`]).
    async fn decide(&self, connect: &Connect, row: &AnyRow) -> Result<Admission, StoreError> {
        let identity = &connect.identity;
        if row.try_get::<i64, _>("accounts")? == 0 {
            return Ok(Admission::Refused(format!(
                "no account for domain token {:?}",
                connect.domaintoken
            )));
        }
        let subscribed = row.try_get::<i64, _>("subscribed")? > 0;
        let Some(domain) = row.try_get::<Option<String>, _>("domain")? else {
            return Ok(Admission::FirstContact { subscribed });
        };
        let hash: Option<String> = row.try_get("token_hash")?;
        let next: Option<String> = row.try_get("token_next")?;
        let board: String = row.try_get("boardhash")?;
        if domain != connect.domaintoken {
            return Ok(Admission::Refused(
                "domain token differs from the registered one".into(),
            ));
        }
        let known = |token_set| {
            Admission::Known(Known {
                board_was: (board != identity.boardhash).then(|| board.clone()),
                token_set,
                subscribed,
            })
        };
        Ok(match (hash, identity.cloudtoken.as_deref()) {
            (None, _) => Admission::FirstContact { subscribed },
            (Some(h), Some(t)) if nxg::digest::matches(&h, &digest(t)) => {
                known(row.try_get("token_set")?)
            }
            // The gateway stored the token of a rotation whose answer the portal did not see.
            (Some(_), Some(t)) if next.is_some_and(|n| nxg::digest::matches(&n, &digest(t))) => {
                self.set_token(&lift_id(identity), t).await?;
                known(now_ms())
            }
            (Some(_), Some(_)) => Admission::Refused("wrong cloud token".into()),
            (Some(_), None) => Admission::Refused("no cloud token although one was issued".into()),
        })
    }

    /// Write `records` in order, in one transaction (a storm of reconnects costs one commit
    /// per batch, not one per gateway). `last_seen` only moves forward, so a record written
    /// late never takes it back.
    pub async fn record(&self, records: &[GatewayRecord]) -> Result<(), StoreError> {
        let mut tx = self.pool.begin().await?;
        for record in records {
            match record {
                GatewayRecord::Connected {
                    identity,
                    domain,
                    api,
                    at,
                } => {
                    sqlx::query(
                        "INSERT INTO gateways (id, vendorid, productcode, sernum, liftnum, hardware, software, boardhash, domain, api, token_hash, last_seen) \
                         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, NULL, $11) \
                         ON CONFLICT (id) DO UPDATE SET liftnum = $5, hardware = $6, software = $7, boardhash = $8, api = $10, \
                         last_seen = CASE WHEN gateways.last_seen > $11 THEN gateways.last_seen ELSE $11 END",
                    )
                    .bind(lift_id(identity))
                    .bind(i64::from(identity.vendorid))
                    .bind(i64::from(identity.productcode))
                    .bind(&identity.sernum)
                    .bind(&identity.liftnum)
                    .bind(&identity.hardware)
                    .bind(&identity.software)
                    .bind(&identity.boardhash)
                    .bind(domain)
                    .bind(i64::from(*api))
                    .bind(*at)
                    .execute(&mut *tx)
                    .await?;
                }
                GatewayRecord::Seen { lift, at } => {
                    sqlx::query(
                        "UPDATE gateways SET last_seen = $1 WHERE id = $2 AND last_seen < $1",
                    )
                    .bind(*at)
                    .bind(lift)
                    .execute(&mut *tx)
                    .await?;
                }
                GatewayRecord::Token { lift, digest, at } => {
                    sqlx::query(
                        "UPDATE gateways SET token_hash = $1, token_set = $2, token_next = NULL WHERE id = $3",
                    )
                    .bind(digest)
                    .bind(*at)
                    .bind(lift)
                    .execute(&mut *tx)
                    .await?;
                }
            }
        }
        tx.commit().await?;
        Ok(())
    }

    /// The gateway of `lift` confirmed `token` ([`GatewayRecord::Token`]), written at once.
    pub async fn set_token(&self, lift: &str, token: &str) -> Result<(), StoreError> {
        self.record(&[GatewayRecord::token(lift, token)]).await
    }

    /// `token` is about to be sent to the gateway in place of its current one (NXg §5.4): until
    /// the gateway confirms it, a CONNECT with either is the gateway's, so an answer lost with
    /// the connection does not lock the gateway out.
    pub async fn set_next_token(&self, lift: &str, token: &str) -> Result<(), StoreError> {
        sqlx::query("UPDATE gateways SET token_next = $1 WHERE id = $2")
            .bind(digest(token))
            .bind(lift)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Forget the token of `lift` (of `domain`) for `by`, audited: its next CONNECT is a first
    /// contact and gets a new one, for a gateway that was replaced or wiped. False when there
    /// is no such lift.
    pub async fn reset_token(
        &self,
        domain: &str,
        lift: &str,
        by: &str,
    ) -> Result<bool, StoreError> {
        let done = sqlx::query(
            "UPDATE gateways SET token_hash = NULL, token_next = NULL, token_set = 0 WHERE id = $1 AND domain = $2",
        )
        .bind(lift)
        .bind(domain)
        .execute(&self.pool)
        .await?;
        if done.rows_affected() == 0 {
            return Ok(false);
        }
        self.audit(&AuditEntry {
            at: now_ms(),
            account: by.to_owned(),
            lift: lift.to_owned(),
            action: "token reset".into(),
            object: "cloud token".into(),
            old_value: None,
            new_value: "(none: first contact next)".into(),
            result: "ok".into(),
        })
        .await?;
        Ok(true)
    }

    /// The domain (account) a registered lift belongs to.
    pub async fn domain_of(&self, lift: &str) -> Result<Option<String>, StoreError> {
        let row = sqlx::query("SELECT domain FROM gateways WHERE id = $1")
            .bind(lift)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.map(|r| r.try_get("domain")).transpose()?)
    }

    /// Record a refused connection attempt.
    pub async fn refused(&self, lift: &str, peer: &str, cause: &str) -> Result<(), StoreError> {
        sqlx::query("INSERT INTO refused (at, lift, peer, cause) VALUES ($1, $2, $3, $4)")
            .bind(now_ms())
            .bind(lift)
            .bind(peer)
            .bind(cause)
            .execute(&self.pool)
            .await?;
        Ok(())
    }

    /// Refused attempts for a lift, newest first: (at, peer, cause).
    pub async fn refusals(&self, lift: &str) -> Result<Vec<(i64, String, String)>, StoreError> {
        let rows =
            sqlx::query("SELECT at, peer, cause FROM refused WHERE lift = $1 ORDER BY at DESC")
                .bind(lift)
                .fetch_all(&self.pool)
                .await?;
        rows.iter()
            .map(|r| Ok((r.try_get("at")?, r.try_get("peer")?, r.try_get("cause")?)))
            .collect()
    }

    fn lift_from(row: &AnyRow) -> Result<LiftRecord, sqlx::Error> {
        Ok(LiftRecord {
            id: row.try_get("id")?,
            vendorid: row.try_get::<i64, _>("vendorid")? as u32,
            productcode: row.try_get::<i64, _>("productcode")? as u32,
            sernum: row.try_get("sernum")?,
            liftnum: row.try_get("liftnum")?,
            hardware: row.try_get("hardware")?,
            software: row.try_get("software")?,
            domain: row.try_get("domain")?,
            api: row.try_get::<i64, _>("api")? as u32,
            last_seen: row.try_get("last_seen")?,
        })
    }

    /// The id of every lift on record.
    pub async fn lift_ids(&self) -> Result<Vec<String>, StoreError> {
        let rows = sqlx::query("SELECT id FROM gateways")
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(|r| r.try_get("id"))
            .collect::<Result<_, _>>()
            .map_err(StoreError::from)
    }

    /// The lifts of `domain`.
    pub async fn lifts(&self, domain: &str) -> Result<Vec<LiftRecord>, StoreError> {
        let rows = sqlx::query("SELECT * FROM gateways WHERE domain = $1 ORDER BY id")
            .bind(domain)
            .fetch_all(&self.pool)
            .await?;
        Ok(rows
            .iter()
            .map(Store::lift_from)
            .collect::<Result<_, _>>()?)
    }

    /// One lift, if `domain` owns it.
    pub async fn lift(&self, domain: &str, id: &str) -> Result<Option<LiftRecord>, StoreError> {
        let row = sqlx::query("SELECT * FROM gateways WHERE id = $1 AND domain = $2")
            .bind(id)
            .bind(domain)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.as_ref().map(Store::lift_from).transpose()?)
    }

    /// Store pushed values, all or none: on PostgreSQL by one binary `COPY`, on SQLite by
    /// multi-row INSERTs in one transaction.
    pub async fn telemetry(&self, batch: &[TelemetryRow]) -> Result<(), StoreError> {
        if let Some(pg) = &self.copy {
            let mut copy = pg
                .copy_in_raw(
                    "COPY telemetry (lift, mplex, node, value, at) FROM STDIN (FORMAT binary)",
                )
                .await?;
            copy.send(copy_binary(batch)).await?;
            copy.finish().await?;
            return Ok(());
        }
        // SQLite: multi-row INSERTs of 512 rows (2,560 parameters: far within SQLite's 32,766)
        // and the rest in chunks of 256, 128, … 1 by its binary digits: sqlx keeps each
        // statement prepared per connection, and ten sizes are at most ten statements (a
        // remainder of any length had been one more, each a VM of tens of KiB, up to sqlx's
        // 100 per connection). Anonymous parameters, because sqlx looks every numbered one up
        // by name, a linear search in SQLite: quadratic per statement.
        let mut tx = self.pool.begin().await?;
        for rows in chunks_by_binary_digits(batch, 512) {
            let mut sql =
                String::from("INSERT INTO telemetry (lift, mplex, node, value, at) VALUES ");
            sql.push_str(&vec!["(?, ?, ?, ?, ?)"; rows.len()].join(", "));
            let mut query = sqlx::query(&sql);
            for row in rows {
                query = query
                    .bind(&row.lift)
                    .bind(&row.mplex)
                    .bind(i64::from(row.node))
                    .bind(&row.value)
                    .bind(row.at);
            }
            query.execute(&mut *tx).await?;
        }
        tx.commit().await?;
        Ok(())
    }

    /// Stored values of one object between `from` and `to` (ms), oldest first: (at, value). At
    /// most the newest 10,000 of the range.
    pub async fn history(
        &self,
        lift: &str,
        mplex: &str,
        from: i64,
        to: i64,
    ) -> Result<Vec<(i64, String)>, StoreError> {
        let rows = sqlx::query(
            "SELECT at, value FROM (SELECT at, value FROM telemetry WHERE lift = $1 AND mplex = $2 AND at >= $3 AND at <= $4 ORDER BY at DESC LIMIT 10000) newest ORDER BY at",
        )
        .bind(lift)
        .bind(mplex)
        .bind(from)
        .bind(to)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| Ok((r.try_get("at")?, r.try_get("value")?)))
            .collect()
    }

    /// The newest stored value of each of `mplexes` (those with none are absent): mplex →
    /// (at, value). One statement for all, each of its parts one indexed look-up
    /// (`telemetry_by_object`): a statement per object had cost the lift page nine round trips
    /// to the database, each with its own pooled connection (on SQLite two thread hand-offs and
    /// a ping apiece), more than the rest of the page.
    pub async fn latest(
        &self,
        lift: &str,
        mplexes: &[String],
    ) -> Result<HashMap<String, (i64, String)>, StoreError> {
        if mplexes.is_empty() {
            return Ok(HashMap::new());
        }
        let sql = (2..mplexes.len() + 2)
            .map(|k| {
                format!(
                    "SELECT * FROM (SELECT mplex, at, value FROM telemetry WHERE lift = $1 AND mplex = ${k} ORDER BY at DESC LIMIT 1) o{k}"
                )
            })
            .collect::<Vec<_>>()
            .join(" UNION ALL ");
        let query = mplexes
            .iter()
            .fold(sqlx::query(&sql).bind(lift), |q, m| q.bind(m));
        query
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(|r| Ok((r.try_get("mplex")?, (r.try_get("at")?, r.try_get("value")?))))
            .collect()
    }

    /// Delete telemetry older than `before` (ms); how many values went.
    pub async fn forget_telemetry(&self, before: i64) -> Result<u64, StoreError> {
        let done = sqlx::query("DELETE FROM telemetry WHERE at < $1")
            .bind(before)
            .execute(&self.pool)
            .await?;
        Ok(done.rows_affected())
    }

    /// Add an audit entry.
    pub async fn audit(&self, e: &AuditEntry) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO audit (at, account, lift, action, object, old_value, new_value, result) VALUES ($1, $2, $3, $4, $5, $6, $7, $8)",
        )
        .bind(e.at)
        .bind(&e.account)
        .bind(&e.lift)
        .bind(&e.action)
        .bind(&e.object)
        .bind(&e.old_value)
        .bind(&e.new_value)
        .bind(&e.result)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// The audit entries of `domain`'s lifts, newest first.
    pub async fn audit_log(&self, domain: &str) -> Result<Vec<AuditEntry>, StoreError> {
        let rows = sqlx::query(
            "SELECT a.* FROM audit a JOIN gateways g ON g.id = a.lift WHERE g.domain = $1 ORDER BY a.at DESC LIMIT 1000",
        )
        .bind(domain)
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(AuditEntry {
                    at: r.try_get("at")?,
                    account: r.try_get("account")?,
                    lift: r.try_get("lift")?,
                    action: r.try_get("action")?,
                    object: r.try_get("object")?,
                    old_value: r.try_get("old_value")?,
                    new_value: r.try_get("new_value")?,
                    result: r.try_get("result")?,
                })
            })
            .collect::<Result<_, sqlx::Error>>()
            .map_err(StoreError::from)
    }
}

/// Telemetry rows in PostgreSQL's binary `COPY` format (PostgreSQL manual, "COPY", §Binary
/// Format): the signature, flags and header extension length, then per row the number of
/// fields and each field as its length and bytes (text as UTF-8, bigint as 8 bytes big-endian),
/// then the trailer -1. Nothing to escape and nothing to parse on the server.
fn copy_binary(batch: &[TelemetryRow]) -> Vec<u8> {
    const SIGNATURE: &[u8] = b"PGCOPY\n\xff\r\n\0";
    let text: usize = batch
        .iter()
        .map(|r| r.lift.len() + r.mplex.len() + r.value.len())
        .sum();
    let mut out = Vec::with_capacity(SIGNATURE.len() + 10 + batch.len() * 42 + text);
    out.extend_from_slice(SIGNATURE);
    out.extend_from_slice(&0i32.to_be_bytes()); // flags: no OIDs
    out.extend_from_slice(&0i32.to_be_bytes()); // no header extension
    let field = |out: &mut Vec<u8>, bytes: &[u8]| {
        // A value longer than 2 GiB cannot have come through a WebSocket message.
        let len = i32::try_from(bytes.len()).unwrap_or(i32::MAX);
        out.extend_from_slice(&len.to_be_bytes());
        out.extend_from_slice(bytes);
    };
    for row in batch {
        out.extend_from_slice(&5i16.to_be_bytes());
        field(&mut out, row.lift.as_bytes());
        field(&mut out, row.mplex.as_bytes());
        field(&mut out, &i64::from(row.node).to_be_bytes());
        field(&mut out, row.value.as_bytes());
        field(&mut out, &row.at.to_be_bytes());
    }
    out.extend_from_slice(&(-1i16).to_be_bytes());
    out
}

/// `rows` rows of `columns` numbered parameters for a statement's `VALUES` or `IN` list:
/// `($1, $2), ($3, $4)`.
fn parameter_rows(rows: usize, columns: usize) -> String {
    (0..rows)
        .map(|row| {
            let row: Vec<String> = (1..=columns)
                .map(|column| format!("${}", row * columns + column))
                .collect();
            format!("({})", row.join(", "))
        })
        .collect::<Vec<_>>()
        .join(", ")
}

/// `items` in chunks of `largest` (a power of two), then the rest in chunks of the powers of two
/// of its binary digits, largest first: every chunk has one of log2(`largest`) + 1 lengths.
fn chunks_by_binary_digits<T>(items: &[T], largest: usize) -> impl Iterator<Item = &[T]> {
    let mut rest = items;
    std::iter::from_fn(move || {
        if rest.is_empty() {
            return None;
        }
        let len = largest.min(1 << rest.len().ilog2());
        let (chunk, tail) = rest.split_at(len);
        rest = tail;
        Some(chunk)
    })
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// What a test's subscriber writes.
    #[derive(Clone, Default)]
    struct Captured(std::sync::Arc<std::sync::Mutex<Vec<u8>>>);

    impl std::io::Write for Captured {
        fn write(&mut self, bytes: &[u8]) -> std::io::Result<usize> {
            self.0.lock().unwrap().extend_from_slice(bytes);
            Ok(bytes.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }

    impl Captured {
        /// A subscriber writing here (from info up), this thread's until the guard is dropped.
        fn install(&self) -> tracing::subscriber::DefaultGuard {
            let writer = self.clone();
            let subscriber = tracing_subscriber::fmt()
                .with_ansi(false)
                .with_writer(move || writer.clone())
                .finish();
            tracing::subscriber::set_default(subscriber)
        }

        fn text(&self) -> String {
            String::from_utf8(self.0.lock().unwrap().clone()).unwrap()
        }
    }

    #[tokio::test(flavor = "current_thread")]
    async fn a_slow_statement_is_one_short_warning() {
        let captured = Captured::default();
        let _during_this_test = captured.install();
        assert_eq!(timed("telemetry", 512, async { 7 }).await, 7);
        let slow = timed("telemetry", 512, async { std::thread::sleep(SLOW) });
        slow.await;
        let text = captured.text();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 1, "{text}");
        assert!(lines[0].contains("WARN"), "{text}");
        assert!(lines[0].contains("slow database statement"), "{text}");
        assert!(lines[0].contains("rows=512"), "{text}");
        assert!(lines[0].contains("what=\"telemetry\""), "{text}");
    }

    /// sqlx's own warning (the statement's whole text) is not written at the portal's levels.
    /// PostgreSQL: its statements are logged on the task that awaits them (SQLite's on the
    /// connection's thread, beyond this test's subscriber).
    #[tokio::test(flavor = "current_thread")]
    async fn sqlx_does_not_write_slow_statements_out() {
        let Some(url) = testkit::postgres("slowlog").await else {
            return;
        };
        let store = Store::open_pooled(&url, 2).await.unwrap();
        let captured = Captured::default();
        let _during_this_test = captured.install();
        let started = std::time::Instant::now();
        sqlx::query("SELECT pg_sleep(1.1)")
            .execute(&store.pool)
            .await
            .unwrap();
        assert!(started.elapsed() >= SLOW);
        assert_eq!(captured.text(), "");
    }

    #[test]
    fn digests_are_hex_of_the_hash() {
        // FIPS 180-2's SHA-256 example; the SHA-1 of "password" in upper case, as NXg §6.4 carries it.
        assert_eq!(
            digest("abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(
            passhash("password"),
            "5BAA61E4C9B93F3F0682250B6CF8331B7EE68FD8"
        );
        let s = secret("clk_");
        assert!(
            s.len() == 36 && s[4..].bytes().all(|b| b.is_ascii_hexdigit()),
            "{s}"
        );
    }

    #[test]
    fn batches_are_cut_into_few_lengths() {
        let items: Vec<u32> = (0..16_384 + 1_000 + 7).collect();
        let chunks: Vec<&[u32]> = chunks_by_binary_digits(&items, 512).collect();
        let lengths: std::collections::BTreeSet<usize> = chunks.iter().map(|c| c.len()).collect();
        assert!(
            lengths.iter().all(|l| l.is_power_of_two() && *l <= 512),
            "{lengths:?}"
        );
        assert_eq!(chunks.iter().filter(|c| c.len() == 512).count(), 33);
        // 17,391 = 33 × 512 + 495, and 495 = 256 + 128 + 64 + 32 + 8 + 4 + 2 + 1.
        assert_eq!(
            chunks.iter().map(|c| c.len()).skip(33).collect::<Vec<_>>(),
            vec![256, 128, 64, 32, 8, 4, 2, 1]
        );
        assert_eq!(chunks.concat(), items);
        assert_eq!(chunks_by_binary_digits::<u32>(&[], 512).count(), 0);
    }

    #[test]
    fn parameter_rows_are_numbered_across_rows() {
        assert_eq!(parameter_rows(2, 3), "($1, $2, $3), ($4, $5, $6)");
        assert_eq!(parameter_rows(3, 1), "($1), ($2), ($3)");
    }

    /// A CONNECT of gateway `sernum` (vendor 1050, product 4096) to `domain`.
    pub(crate) fn connect(sernum: &str, domain: &str, token: Option<&str>) -> Connect {
        Connect {
            identity: Identity {
                sernum: sernum.into(),
                vendorid: 1050,
                productcode: 4096,
                liftnum: String::new(),
                hardware: String::new(),
                software: String::new(),
                api: 1,
                boardhash: String::new(),
                cloudtoken: token.map(str::to_owned),
            },
            domaintoken: domain.into(),
        }
    }

    fn telemetry_row(lift: &str, value: &str, at: i64) -> TelemetryRow {
        TelemetryRow {
            lift: lift.into(),
            mplex: "0x652001".into(),
            node: 1,
            value: value.into(),
            at,
        }
    }

    #[tokio::test]
    async fn sqlite() {
        let store = Store::open("sqlite::memory:").await.unwrap();
        assert_eq!(store.free_connections().await.unwrap(), None);
        a_large_batch_is_stored_exactly(&store).await;
        records_refresh_rows_and_last_seen_only_moves_forward(&store).await;
        accounts_tokens_and_isolation(store).await;
    }

    #[tokio::test]
    async fn postgres() {
        let Some(url) = testkit::postgres("store").await else {
            return;
        };
        let store = Store::open_pooled(&url, 3).await.unwrap();
        // Other tests share the server, so only a range: this store's own connection counts.
        let free = store.free_connections().await.unwrap().expect("PostgreSQL");
        assert!((0..100_000).contains(&free), "{free} free connections");
        a_large_batch_is_stored_exactly(&store).await;
        records_refresh_rows_and_last_seen_only_moves_forward(&store).await;
        accounts_tokens_and_isolation(store).await;
    }

    /// Every value of a batch larger than one statement comes back as it went in: texts with
    /// quotes, tabs, backslashes, line breaks and several scripts, node 127, times beyond 32 bits
    /// (the COPY encoding on PostgreSQL, the chunked INSERTs on SQLite).
    async fn a_large_batch_is_stored_exactly(store: &Store) {
        let lift = "1050-4096-BATCH";
        let texts = [
            "",
            "0",
            "it's \"quoted\"",
            "tab\tback\\slash\nline",
            "Türe offen — 扉",
            "\\N",
        ];
        let batch: Vec<TelemetryRow> = (0..2_345)
            .map(|i| TelemetryRow {
                lift: lift.into(),
                mplex: "0x652001".into(),
                node: (i % 128) as u8,
                value: format!("{}{i}", texts[i % texts.len()]),
                at: 5_000_000_000 + i as i64,
            })
            .collect();
        store.telemetry(&batch).await.unwrap();
        let stored = store.history(lift, "0x652001", 0, i64::MAX).await.unwrap();
        let sent: Vec<(i64, String)> = batch.iter().map(|r| (r.at, r.value.clone())).collect();
        assert_eq!(stored, sent);
        let nodes: Vec<i64> = sqlx::query("SELECT node FROM telemetry WHERE lift = $1 ORDER BY at")
            .bind(lift)
            .fetch_all(&store.pool)
            .await
            .unwrap()
            .iter()
            .map(|r| r.get::<i64, _>("node"))
            .collect();
        assert_eq!(
            nodes,
            batch.iter().map(|r| i64::from(r.node)).collect::<Vec<_>>()
        );
        assert_eq!(store.forget_telemetry(6_000_000_000).await.unwrap(), 2_345);
    }

    /// A gateway's rows as [`Store::record`] writes them, one batch with repeats of a gateway:
    /// its last identity wins, and `last_seen` never moves back (a record written late).
    async fn records_refresh_rows_and_last_seen_only_moves_forward(store: &Store) {
        store.add_account("records", "REC").await.unwrap();
        let connected = |software: &str, at: i64| {
            let mut connect = connect("REC-1", "REC", None);
            connect.identity.software = software.into();
            let mut record = GatewayRecord::connected(&connect, 2);
            if let GatewayRecord::Connected { at: when, .. } = &mut record {
                *when = at;
            }
            record
        };
        let lift = lift_id(&connect("REC-1", "REC", None).identity);
        let seen = |at| GatewayRecord::Seen {
            lift: lift.clone(),
            at,
        };
        let row = || async { store.lift("REC", &lift).await.unwrap().unwrap() };
        store
            .record(&[connected("v1", 1_000), seen(2_000), connected("v2", 3_000)])
            .await
            .unwrap();
        assert_eq!(
            (row().await.software, row().await.last_seen),
            ("v2".into(), 3_000)
        );
        store
            .record(&[seen(2_500), connected("v3", 2_600)])
            .await
            .unwrap();
        assert_eq!(
            (row().await.software, row().await.last_seen),
            ("v3".into(), 3_000)
        );
        store.record(&[seen(4_000)]).await.unwrap();
        assert_eq!(row().await.last_seen, 4_000);
    }

    async fn accounts_tokens_and_isolation(store: Store) {
        let key = store.add_account("masora", "MAS").await.unwrap();
        assert!(key.starts_with("clk_") && key.len() == 36);
        assert_eq!(
            store
                .operator_by_key(&key)
                .await
                .unwrap()
                .unwrap()
                .account
                .domain,
            "MAS"
        );
        assert!(store.operator_by_key("clk_wrong").await.unwrap().is_none());
        assert!(
            store.add_account("again", "MAS").await.is_err(),
            "one account per domain"
        );
        let gw = |token| connect("180917010200000102", "MAS", token);
        assert_eq!(
            store.admit(&gw(None)).await.unwrap(),
            Admission::FirstContact { subscribed: false }
        );
        assert!(matches!(
            store.admit(&connect("1", "XYZ", None)).await.unwrap(),
            Admission::Refused(_)
        ));
        store
            .record(&[GatewayRecord::connected(&gw(None), 1)])
            .await
            .unwrap();
        // Not confirmed yet: still first contact.
        assert_eq!(
            store.admit(&gw(Some("x"))).await.unwrap(),
            Admission::FirstContact { subscribed: false }
        );
        store
            .set_token(&lift_id(&gw(None).identity), "T0K3N")
            .await
            .unwrap();
        assert!(matches!(
            store.admit(&gw(Some("T0K3N"))).await.unwrap(),
            Admission::Known(Known { board_was: None, token_set, subscribed: false }) if token_set > 0
        ));
        // Once a user holds a subscription of the lift, its admission says so.
        let lift = lift_id(&gw(None).identity);
        let held = ["0x652001".to_owned()];
        store
            .subscribe_objects(&lift, "masora", &held, 0, 0.0)
            .await
            .unwrap();
        assert!(matches!(
            store.admit(&gw(Some("T0K3N"))).await.unwrap(),
            Admission::Known(Known {
                subscribed: true,
                ..
            })
        ));
        store
            .unsubscribe_objects(&lift, "masora", &held)
            .await
            .unwrap();
        assert!(matches!(
            store.admit(&gw(Some("T0K3N"))).await.unwrap(),
            Admission::Known(Known {
                subscribed: false,
                ..
            })
        ));
        assert!(
            matches!(store.admit(&gw(Some("T0K3M"))).await.unwrap(), Admission::Refused(c) if c.contains("wrong"))
        );
        // A registered gateway naming a domain no account has (the same statement reads both).
        assert!(matches!(
            store.admit(&connect("180917010200000102", "XYZ", Some("T0K3N"))).await.unwrap(),
            Admission::Refused(c) if c.contains("no account")
        ));
        assert!(matches!(
            store.admit(&gw(None)).await.unwrap(),
            Admission::Refused(_)
        ));
        // Only digests are stored.
        let row = sqlx::query("SELECT token_hash FROM gateways WHERE domain = 'MAS'")
            .fetch_one(&store.pool)
            .await
            .unwrap();
        assert_eq!(row.get::<String, _>("token_hash"), digest("T0K3N"));
        store.add_account("other", "OTH").await.unwrap();
        assert_eq!(store.lifts("MAS").await.unwrap().len(), 1);
        assert!(store.lifts("OTH").await.unwrap().is_empty());
        assert!(store
            .lift("OTH", "1050-4096-180917010200000102")
            .await
            .unwrap()
            .is_none());
        store
            .telemetry(&[telemetry_row("1050-4096-180917010200000102", "7", 100)])
            .await
            .unwrap();
        let h = store
            .history("1050-4096-180917010200000102", "0x652001", 0, 200)
            .await
            .unwrap();
        assert_eq!(h, [(100, "7".to_owned())]);
        // Retention: values older than the cut go, newer ones stay; latest sees the newest.
        let lift = "1050-4096-180917010200000102";
        store
            .telemetry(&[telemetry_row(lift, "8", 300)])
            .await
            .unwrap();
        let door = TelemetryRow {
            mplex: "0x630101".into(),
            ..telemetry_row(lift, "3", 250)
        };
        store.telemetry(&[door]).await.unwrap();
        let asked = ["0x652001", "0x630101", "0x100100"].map(String::from);
        let latest = store.latest(lift, &asked).await.unwrap();
        assert_eq!(latest.len(), 2, "{latest:?}");
        assert_eq!(latest["0x652001"], (300, "8".to_owned()));
        assert_eq!(latest["0x630101"], (250, "3".to_owned()));
        assert!(store.latest(lift, &[]).await.unwrap().is_empty());
        assert_eq!(store.forget_telemetry(200).await.unwrap(), 1);
        let h = store.history(lift, "0x652001", 0, 1000).await.unwrap();
        assert_eq!(h, [(300, "8".to_owned())]);
        token_lifecycle_and_board(&store).await;
        users::tests::users_keys_and_the_epoch(&store).await;
        subscriptions::tests::held_released_and_per_lift(&store).await;
        ticket_keys::tests::made_once_replaced_over_the_version(&store).await;
        alarms::tests::one_active_alarm_per_condition(&store).await;
    }

    /// Rotation (old and new token both admitted until one is confirmed), reset (first contact
    /// again, only by the lift's own account), and a board that changed under a valid token.
    async fn token_lifecycle_and_board(store: &Store) {
        let gw = |token: Option<&str>| connect("180917010200000102", "MAS", token);
        let lift = lift_id(&gw(None).identity);
        store.set_next_token(&lift, "N3XT").await.unwrap();
        let known = |a: Admission| matches!(a, Admission::Known(_));
        assert!(known(store.admit(&gw(Some("T0K3N"))).await.unwrap()));
        // The gateway stored the new token but its answer was lost: admitted, and it counts.
        assert!(known(store.admit(&gw(Some("N3XT"))).await.unwrap()));
        assert!(
            matches!(
                store.admit(&gw(Some("T0K3N"))).await.unwrap(),
                Admission::Refused(_)
            ),
            "the old token is over once the new one was used"
        );
        let mut swapped = gw(Some("N3XT"));
        swapped.identity.boardhash = "B0ARD2".into();
        assert!(matches!(
            store.admit(&swapped).await.unwrap(),
            Admission::Known(Known { board_was: Some(b), .. }) if b.is_empty()
        ));
        assert!(
            !store.reset_token("OTH", &lift, "x").await.unwrap(),
            "not OTH's lift"
        );
        assert!(!store.reset_token("MAS", "1-2-3", "x").await.unwrap());
        assert!(store.reset_token("MAS", &lift, "ops").await.unwrap());
        let audit = store.audit_log("MAS").await.unwrap();
        assert_eq!(
            (audit[0].action.as_str(), audit[0].account.as_str()),
            ("token reset", "ops")
        );
        assert_eq!(
            store.admit(&gw(Some("N3XT"))).await.unwrap(),
            Admission::FirstContact { subscribed: false }
        );
        assert_eq!(
            store.domain_of(&lift).await.unwrap().as_deref(),
            Some("MAS")
        );
    }

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
