//! What the portal keeps (docs/PORTAL.md §Stores), in SQLite or PostgreSQL through sqlx (one
//! set of portable statements with `$n` parameters), one module per table or group of tables:
//! [`accounts`], the gateway registry ([`gateways`]: identities, token digests, last heard),
//! refused connection attempts ([`refused`]), pushed values ([`telemetry`]), the audit log
//! ([`audit`]), bus events, alarms and the webhook outbox ([`alarms`]), users and their API keys
//! ([`users`]), browser sessions ([`sessions`]), elevation grants ([`elevations`]), users'
//! subscriptions ([`subscriptions`]), a cluster's TLS ticket keys ([`ticket_keys`]) and what
//! lift insights read and keep ([`insights`]); the tables and their migrations in [`schema`].
//!
//! Secrets are stored only as SHA-256 digests (API keys, cloud tokens, session cookies:
//! [`secrets`]); tokens are compared with the one on record in time independent of where they
//! differ.

#![warn(missing_docs)]

pub mod accounts;
pub mod alarms;
pub mod audit;
pub mod backup;
pub mod elevations;
pub mod gateways;
pub mod health;
pub mod history;
pub mod idempotency;
pub mod insights;
pub mod refused;
pub mod rollups;
pub mod schema;
pub mod secrets;
pub mod sessions;
pub mod subscriptions;
pub mod telemetry;
pub mod ticket_keys;
pub mod turns;
pub mod users;

pub use alarms::{new_id, AlarmFilter, EventRow, OutboxEntry};
pub use elevations::ElevationGrant;
pub use gateways::{GatewayRecord, GatewayRow, Registered};
pub use health::{Health, Trouble};
pub use history::{Buckets, Source};
pub use idempotency::Idempotent;
pub use insights::{Edges, Lifts, Statement, StatusRow, Timeline};
pub use refused::Refusal;
pub use rollups::{Bucket, Grain, RolledUp};
pub use secrets::{digest, passhash, secret};
pub use sessions::SessionRecord;
pub use subscriptions::StoredSubscription;
pub use telemetry::TelemetryRow;
pub use turns::Turn;
pub use users::{secret_matches, UserError};

use sqlx::any::AnyPoolOptions;
use sqlx::{AnyPool, ConnectOptions, Connection, Executor, Row};

/// A pooled PostgreSQL connection idle this long is pinged before it is used
/// ([`Store::open_pooled`]).
const PING_IDLE: std::time::Duration = std::time::Duration::from_secs(1);

/// A statement slower than this is worth a warning ([`timed`]).
const SLOW: std::time::Duration = std::time::Duration::from_secs(1);

/// `statement` (`rows` rows of `what`), with one short warning when it took longer than a second.
/// sqlx's own warning about slow statements is turned down to debug (`quiet`): it
/// carries the statement's whole text, kilobytes for a batch, once per batch while the database
/// is slow.
pub async fn timed<T>(
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
    /// The store is closed: the portal is stopping and nobody is left to ask.
    pub fn closed() -> StoreError {
        StoreError::from(sqlx::Error::PoolClosed)
    }

    /// A statement found no row where one was expected.
    pub fn no_row() -> StoreError {
        StoreError::from(sqlx::Error::RowNotFound)
    }

    /// The trouble the database is in, if the failure is one that passes (a full disk, a busy
    /// or unreachable database) rather than a refusal of the statement.
    pub fn trouble(&self) -> Option<Trouble> {
        Trouble::of(&self.0)
    }

    /// Whether the failure passes ([`StoreError::trouble`]): worth trying again later.
    pub fn is_unavailable(&self) -> bool {
        self.trouble().is_some()
    }
}

/// The portal's database.
#[derive(Clone)]
pub struct Store {
    pool: AnyPool,
    /// PostgreSQL only: connections of its own driver for telemetry by binary `COPY`, which
    /// sqlx's database-neutral driver does not offer.
    copy: Option<sqlx::PgPool>,
    keys: std::sync::Arc<users::KeyCache>,
    /// The auth epoch this process has seen (see `users`); sessions older than it are checked
    /// again.
    epoch: std::sync::Arc<std::sync::atomic::AtomicI64>,
    /// Whether the database takes writes now.
    health: std::sync::Arc<Health>,
    /// The earliest time (ms) of values stored late since the last roll-up (`i64::MAX`: none):
    /// their minutes are rolled up again ([`Store::rewind_roll_ups`]).
    rewind: std::sync::Arc<std::sync::atomic::AtomicI64>,
}

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
            // A connection still in a transaction (one whose end failed) is closed, not given
            // to the next caller inside a transaction it did not begin ([`Store::settle`]
            // closes the ones it knows of; this catches the rest).
            .after_release(|conn, _| Box::pin(async move { Ok(!conn.is_in_transaction()) }))
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
                    } else {
                        // The portal's statements are look-ups along indexes and batched
                        // writes: compiling one (JIT) costs more than it saves — a month's
                        // report of 10,000 lifts took 1.7 s with it, 1.3 s without.
                        conn.execute("SET jit = off").await?;
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
        schema::create(&pool, sqlite).await?;
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
            health: std::sync::Arc::default(),
            rewind: std::sync::Arc::new(std::sync::atomic::AtomicI64::new(i64::MAX)),
        })
    }

    /// Whether the database takes writes now, as the writers and the probe saw last.
    pub fn health(&self) -> &Health {
        &self.health
    }

    /// A pooled connection to write on (a failure to get one is noted for [`Store::health`]).
    pub(crate) async fn writer(&self) -> Result<sqlx::pool::PoolConnection<sqlx::Any>, StoreError> {
        let conn = self.pool.acquire().await.map_err(StoreError::from);
        if conn.is_err() {
            self.health.note(&conn);
        }
        conn
    }

    /// The end of a transaction on `conn` (`outcome`: its work and its commit): on a failure
    /// the connection is closed rather than returned to the pool. A COMMIT that failed on a
    /// full disk had left a connection whose transaction never ended: every other writer then
    /// found the database locked, and the later "commits" on it only released savepoints of
    /// that transaction — values counted as stored that were not. Noted for [`Store::health`].
    pub(crate) async fn settle<T>(
        &self,
        conn: sqlx::pool::PoolConnection<sqlx::Any>,
        outcome: Result<T, sqlx::Error>,
    ) -> Result<T, StoreError> {
        if outcome.is_err() {
            let _ = conn.close().await;
        }
        let outcome = outcome.map_err(StoreError::from);
        self.health.note(&outcome);
        outcome
    }

    /// Write the probe row now: whether the database takes a write ([`Store::watch_writes`]).
    pub async fn probe_write(&self) -> Result<(), StoreError> {
        let outcome = sqlx::query(
            "INSERT INTO write_probe (id, at) VALUES (1, $1) ON CONFLICT (id) DO UPDATE SET at = excluded.at",
        )
        .bind(cloud_types::now_ms())
        .execute(&self.pool)
        .await
        .map(|_| ())
        .map_err(StoreError::from);
        self.health.note(&outcome);
        outcome
    }

    /// Probe whether the database takes writes, every `every` while it does and every second
    /// while it does not, for as long as the store lives: a full disk or an outage is noticed
    /// when nothing else writes, and its end within a second of space or the server returning.
    pub async fn watch_writes(self, every: std::time::Duration) {
        loop {
            let wait = match self.probe_write().await {
                Ok(()) => every,
                Err(e) => {
                    tracing::debug!(error = %e, "the database takes no write");
                    std::time::Duration::from_secs(1)
                }
            };
            tokio::time::sleep(wait).await;
        }
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
}

/// `url` as it may be shown in logs and errors: a password in its userinfo
/// (`postgres://USER:PASSWORD@HOST/DB`) or its query (`?password=…`) replaced by `***`.
pub fn shown_url(url: &str) -> String {
    let mut shown = url.to_owned();
    if let Some((scheme, rest)) = url.split_once("://") {
        let end = rest.find(['/', '?']).unwrap_or(rest.len());
        if let Some((userinfo, host)) = rest[..end].rsplit_once('@') {
            if let Some((user, _)) = userinfo.split_once(':') {
                shown = format!("{scheme}://{user}:***@{host}{}", &rest[end..]);
            }
        }
    }
    if let Some((head, query)) = shown.clone().split_once('?') {
        let query: Vec<String> = query
            .split('&')
            .map(|pair| match pair.split_once('=') {
                Some((key, _)) if key.eq_ignore_ascii_case("password") => format!("{key}=***"),
                _ => pair.to_owned(),
            })
            .collect();
        shown = format!("{head}?{}", query.join("&"));
    }
    shown
}

/// `rows` rows of `columns` numbered parameters for a statement's `VALUES` or `IN` list:
/// `($1, $2), ($3, $4)`.
pub(crate) fn parameter_rows(rows: usize, columns: usize) -> String {
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
pub(crate) fn chunks_by_binary_digits<T>(
    items: &[T],
    largest: usize,
) -> impl Iterator<Item = &[T]> {
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
    use cloud_types::lifts::lift_id;
    use cloud_types::users::Account;
    use nxg::msg::Connect;
    use testkit::connect;

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
    fn urls_are_shown_without_passwords() {
        assert_eq!(
            shown_url("postgres://canlift:s3cret@db.example:5432/portal"),
            "postgres://canlift:***@db.example:5432/portal"
        );
        assert_eq!(
            shown_url("postgresql://u:p@h/d?sslmode=require&password=x"),
            "postgresql://u:***@h/d?sslmode=require&password=***"
        );
        assert_eq!(shown_url("postgres://u@h/d"), "postgres://u@h/d");
        assert_eq!(
            shown_url("sqlite://state/canlift.db"),
            "sqlite://state/canlift.db"
        );
        assert_eq!(
            shown_url("postgres://u:p@ss@h/d"),
            "postgres://u:***@h/d",
            "an @ in the password"
        );
    }

    #[test]
    fn parameter_rows_are_numbered_across_rows() {
        assert_eq!(parameter_rows(2, 3), "($1, $2, $3), ($4, $5, $6)");
        assert_eq!(parameter_rows(3, 1), "($1), ($2), ($3)");
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
        means_pass_over_what_is_no_number(&store).await;
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
        means_pass_over_what_is_no_number(&store).await;
        accounts_tokens_and_isolation(store).await;
    }

    /// A trend's means: of the numbers in the window only (text, booleans, empty values and
    /// what only begins like a number passed over, not cast to 0 or refused), per lift.
    async fn means_pass_over_what_is_no_number(store: &Store) {
        store.add_account("means", "MEA").await.unwrap();
        let connect = connect("MEA-1", "MEA", None);
        let lift = lift_id(&connect.identity);
        store
            .record(&[GatewayRecord::connected(&lift, &connect, 2)])
            .await
            .unwrap();
        let rows: Vec<TelemetryRow> =
            ["2000", " 2400 ", "-1e3", "x12", "", "true", "1.5.2", "3000"]
                .iter()
                .enumerate()
                .map(|(i, v)| TelemetryRow {
                    lift: lift.clone(),
                    mplex: "0x440301".into(),
                    node: 0,
                    value: (*v).into(),
                    at: 10_000 + i as i64,
                })
                .collect();
        store.telemetry(&rows).await.unwrap();
        let means = store.means("0x440301", 10_000, 10_007).await.unwrap();
        assert_eq!(
            means.get(&lift),
            Some(&((2000.0 + 2400.0 - 1000.0) / 3.0, 3))
        );
        let means = store.means("0x440301", 10_000, 10_008).await.unwrap();
        assert_eq!(means.get(&lift), Some(&(6400.0 / 4.0, 4)));
        assert!(store.means("0x440301", 0, 10_000).await.unwrap().is_empty());
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
        let stored = store
            .values(lift, "0x652001", 0, i64::MAX, 100_000)
            .await
            .unwrap();
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
            let lift = lift_id(&connect.identity);
            let mut record = GatewayRecord::connected(&lift, &connect, 2);
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
        let account = Account {
            name: "records".into(),
            domain: "REC".into(),
        };
        let row = || async { store.lift(&account, &lift).await.unwrap().unwrap() };
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

    /// What one statement reads for each CONNECT: whether an account has its domain, the
    /// lift's row and token digests, whether users hold subscriptions of it.
    async fn gateway_row(store: &Store, connect: &Connect) -> GatewayRow {
        let mut rows = store.gateway_rows(&[connect]).await.unwrap();
        assert_eq!(rows.len(), 1);
        rows.remove(0)
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
        assert!(store.domain_exists("MAS").await.unwrap());
        assert!(!store.domain_exists("XYZ").await.unwrap());
        let gw = |token| connect("180917010200000102", "MAS", token);
        let lift = lift_id(&gw(None).identity);
        let row = gateway_row(&store, &gw(None)).await;
        assert_eq!(
            row,
            GatewayRow {
                account: Some("masora".into()),
                key: lift.clone(),
                subscribed: false,
                registered: None
            }
        );
        assert!(gateway_row(&store, &connect("1", "XYZ", None))
            .await
            .account
            .is_none());
        store
            .record(&[GatewayRecord::connected(&lift, &gw(None), 1)])
            .await
            .unwrap();
        let registered = gateway_row(&store, &gw(Some("x")))
            .await
            .registered
            .unwrap();
        assert_eq!(
            (registered.domain.as_str(), registered.token_hash),
            ("MAS", None),
            "no token confirmed yet"
        );
        store.set_token(&lift, "MAS", "T0K3N").await.unwrap();
        store.set_next_token(&lift, "N3XT").await.unwrap();
        let registered = gateway_row(&store, &gw(None)).await.registered.unwrap();
        // Only digests are stored.
        assert_eq!(registered.token_hash, Some(digest("T0K3N")));
        assert_eq!(registered.token_next, Some(digest("N3XT")));
        assert!(registered.token_set > 0);
        // Once a user holds a subscription of the lift, its row says so.
        let held = ["0x652001".to_owned()];
        store
            .subscribe_objects(&lift, "masora", &held, 0, 0.0)
            .await
            .unwrap();
        assert!(gateway_row(&store, &gw(None)).await.subscribed);
        store
            .unsubscribe_objects(&lift, "masora", &held)
            .await
            .unwrap();
        assert!(!gateway_row(&store, &gw(None)).await.subscribed);
        // Many CONNECTs in one statement, each with its own row, in their order.
        let other = connect("1", "XYZ", None);
        let rows = store
            .gateway_rows(&[&gw(None), &other, &gw(None)])
            .await
            .unwrap();
        assert_eq!(rows.len(), 3);
        assert!(rows[0].registered.is_some() && rows[2].registered.is_some());
        assert_eq!(
            rows[1],
            GatewayRow {
                key: lift_id(&other.identity),
                ..GatewayRow::default()
            }
        );
        // Reset: only by the lift's own account, audited; the token digests are gone.
        store.add_account("other", "OTH").await.unwrap();
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
        let registered = gateway_row(&store, &gw(None)).await.registered.unwrap();
        assert_eq!((registered.token_hash, registered.token_next), (None, None));
        assert_eq!(
            store.account_of(&lift).await.unwrap().as_deref(),
            Some("masora")
        );
        assert_eq!(store.lifts("MAS").await.unwrap().len(), 1);
        assert!(store.lifts("OTH").await.unwrap().is_empty());
        let other = Account {
            name: "other".into(),
            domain: "OTH".into(),
        };
        assert!(store
            .lift(&other, "1050-4096-180917010200000102")
            .await
            .unwrap()
            .is_none());
        store
            .telemetry(&[telemetry_row("1050-4096-180917010200000102", "7", 100)])
            .await
            .unwrap();
        let h = store
            .values("1050-4096-180917010200000102", "0x652001", 0, 200, 100)
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
        let h = store.values(lift, "0x652001", 0, 1000, 100).await.unwrap();
        assert_eq!(h, [(300, "8".to_owned())]);
        users::tests::users_keys_and_the_epoch(&store).await;
        users::tests::users_of_single_sign_on(&store).await;
        subscriptions::tests::held_released_and_per_lift(&store).await;
        ticket_keys::tests::made_once_replaced_over_the_version(&store).await;
        alarms::tests::one_active_alarm_per_condition(&store).await;
        idempotency::tests::a_key_answers_its_first_outcome(&store).await;
        history::tests::a_week_in_a_thousand_buckets(&store).await;
    }
}
