//! The gateway registry (NXg §5.2, §5.4): one row per lift — its identity, account, token
//! digests and when it was last heard — written in batches and read for admissions and for
//! the operators' lists.

use nxg::msg::{Connect, Identity};
use sqlx::any::AnyRow;
use sqlx::Row;

use cloud_types::lifts::{lift_id, LiftRecord};
use cloud_types::now_ms;
use cloud_types::users::Account;

use crate::secrets::digest;
use crate::{parameter_rows, Store, StoreError};

/// What the registry keeps of a gateway's connections ([`Store::record`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum GatewayRecord {
    /// A gateway was admitted (CONNACK) at `at` (ms since the epoch) as lift `lift` (the
    /// registry's key the admission chose), saying it is `identity` (NXg §5.2.1) of `domain` and
    /// speaking `api`: its row is made or its identity refreshed — never another account's row.
    Connected {
        /// The registry's key.
        lift: String,
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
        /// Lift key.
        lift: String,
        /// When.
        at: i64,
    },
    /// A gateway confirmed a token at `at` (NXg §5.4): only its digest is kept, with the time
    /// (for `[gateways] token_rotate_days`); a rotation in progress is over. Written only to
    /// the row of the lift of `domain`.
    Token {
        /// Lift key.
        lift: String,
        /// The domain token of its account.
        domain: String,
        /// The token's digest.
        digest: String,
        /// When.
        at: i64,
    },
}

impl GatewayRecord {
    /// Lift `lift`'s gateway admitted now after `connect`, speaking `api`.
    pub fn connected(lift: &str, connect: &Connect, api: u32) -> GatewayRecord {
        GatewayRecord::Connected {
            lift: lift.to_owned(),
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
    pub fn lift(&self) -> &str {
        match self {
            GatewayRecord::Connected { lift, .. }
            | GatewayRecord::Seen { lift, .. }
            | GatewayRecord::Token { lift, .. } => lift,
        }
    }

    /// `lift`'s gateway (of `domain`) confirmed `token` now.
    pub fn token(lift: &str, domain: &str, token: &str) -> GatewayRecord {
        GatewayRecord::Token {
            lift: lift.to_owned(),
            domain: domain.to_owned(),
            digest: digest(token),
            at: now_ms(),
        }
    }
}

/// A change to a lift's row and what it takes along, with the audit entry it gets
/// ([`Store::reset_token`], [`Store::retire`]).
struct AuditedChange<'a> {
    /// The statements, in order, each binding the lift's key as `$1` (and the domain as `$2`
    /// where it names one); the first finds the lift's row or there is no such lift.
    statements: &'a [&'a str],
    action: &'a str,
    object: &'a str,
    new_value: &'a str,
}

/// What the registry holds of a CONNECT's lift ([`Store::gateway_rows`]): all an admission
/// decides on.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct GatewayRow {
    /// The account whose domain token the CONNECT gave, if any.
    pub account: Option<String>,
    /// The registry's key of the CONNECT's lift in that account: its row's, or for a lift not
    /// yet registered the plain id — scoped by the account when another account's lift has
    /// that key (`cloud_types::lifts::scoped_key`).
    pub key: String,
    /// Whether users hold subscriptions of the lift (to register when it connects).
    pub subscribed: bool,
    /// The lift's row, if it was ever admitted.
    pub registered: Option<Registered>,
}

/// A registered lift's row, as an admission needs it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Registered {
    /// The domain token it was admitted with.
    pub domain: String,
    /// The boardhash of its last admission.
    pub boardhash: String,
    /// The digest of its token, once one was confirmed (none after a reset).
    pub token_hash: Option<String>,
    /// The digest of the token a rotation sent and the gateway has not confirmed yet.
    pub token_next: Option<String>,
    /// When the token in use was confirmed (ms since the epoch; 0 when not recorded).
    pub token_set: i64,
}

impl GatewayRow {
    fn from_row(row: &AnyRow, id: &str) -> Result<GatewayRow, sqlx::Error> {
        let account: Option<String> = row.try_get("account")?;
        let key = match (row.try_get::<Option<String>, _>("key")?, &account) {
            (Some(key), _) => key,
            (None, Some(account)) if row.try_get::<i64, _>("taken")? > 0 => {
                cloud_types::lifts::scoped_key(id, account)
            }
            (None, _) => id.to_owned(),
        };
        let registered = match row.try_get::<Option<String>, _>("domain")? {
            None => None,
            Some(domain) => Some(Registered {
                domain,
                boardhash: row.try_get("boardhash")?,
                token_hash: row.try_get("token_hash")?,
                token_next: row.try_get("token_next")?,
                token_set: row.try_get("token_set")?,
            }),
        };
        Ok(GatewayRow {
            account,
            key,
            subscribed: row.try_get::<i64, _>("subscribed")? > 0,
            registered,
        })
    }
}

/// Rows of one kind written in one statement at most.
const ROWS_PER_STATEMENT: usize = 256;

/// A [`GatewayRecord::Connected`] row to write: what the last of the records merged into it
/// says, the latest time among them, and which records they were.
struct ConnectedRow<'a> {
    lift: &'a str,
    identity: &'a Identity,
    domain: &'a str,
    api: u32,
    at: i64,
    indexes: Vec<usize>,
}

/// A [`GatewayRecord::Token`] to write.
struct TokenRow<'a> {
    lift: &'a str,
    domain: &'a str,
    digest: &'a str,
    at: i64,
}

/// Records grouped for [`Store::record_batch`].
struct RecordBatch<'a> {
    /// Rows to make or refresh, in rounds: a lift appears once per round, its records of the
    /// n-th account to name it in the n-th.
    connected: Vec<Vec<ConnectedRow<'a>>>,
    /// Lifts last heard, each at its latest.
    seen: Vec<(&'a str, i64)>,
    /// The last token record of each lift and account.
    tokens: Vec<TokenRow<'a>>,
}

impl<'a> RecordBatch<'a> {
    /// `records` cut where grouping would change what they do: a token or a last-heard time
    /// written before its lift's row was made is lost when written in order, so a row of a
    /// lift heard of earlier (or of a lift and account whose token came earlier) starts a batch
    /// of its own. Never so in the portal, which writes a gateway's row before anything else
    /// of it; the rows must end the same all the same.
    fn all(records: &'a [GatewayRecord]) -> Vec<RecordBatch<'a>> {
        use std::collections::HashSet;
        let mut batches = Vec::new();
        let mut start = 0;
        let mut seen: HashSet<&str> = HashSet::new();
        let mut tokens: HashSet<(&str, &str)> = HashSet::new();
        for (i, record) in records.iter().enumerate() {
            match record {
                GatewayRecord::Connected { lift, domain, .. }
                    if seen.contains(lift.as_str())
                        || tokens.contains(&(lift.as_str(), domain.as_str())) =>
                {
                    batches.push(RecordBatch::of(&records[start..i], start));
                    start = i;
                    seen.clear();
                    tokens.clear();
                }
                GatewayRecord::Seen { lift, .. } => {
                    seen.insert(lift);
                }
                GatewayRecord::Token { lift, domain, .. } => {
                    tokens.insert((lift, domain));
                }
                GatewayRecord::Connected { .. } => {}
            }
        }
        batches.push(RecordBatch::of(&records[start..], start));
        batches
    }

    /// `records`, the first of which is the `offset`-th of the batch, grouped.
    fn of(records: &'a [GatewayRecord], offset: usize) -> RecordBatch<'a> {
        use std::collections::HashMap;
        let mut connected: Vec<Vec<ConnectedRow<'a>>> = Vec::new();
        // Per lift, the accounts that named it in order; per (lift, account), its row's place.
        let mut accounts: HashMap<&str, Vec<&str>> = HashMap::new();
        let mut placed: HashMap<(&str, &str), (usize, usize)> = HashMap::new();
        let mut seen: Vec<(&str, i64)> = Vec::new();
        let mut seen_at: HashMap<&str, usize> = HashMap::new();
        let mut tokens: Vec<TokenRow<'a>> = Vec::new();
        let mut token_at: HashMap<(&str, &str), usize> = HashMap::new();
        for (i, record) in (offset..).zip(records) {
            match record {
                GatewayRecord::Connected {
                    lift,
                    identity,
                    domain,
                    api,
                    at,
                } => match placed.get(&(lift.as_str(), domain.as_str())) {
                    Some(&(round, slot)) => {
                        let row = &mut connected[round][slot];
                        row.identity = identity;
                        row.api = *api;
                        row.at = row.at.max(*at);
                        row.indexes.push(i);
                    }
                    None => {
                        let named = accounts.entry(lift).or_default();
                        let round = named.len();
                        named.push(domain);
                        if connected.len() <= round {
                            connected.push(Vec::new());
                        }
                        placed.insert((lift, domain), (round, connected[round].len()));
                        connected[round].push(ConnectedRow {
                            lift,
                            identity,
                            domain,
                            api: *api,
                            at: *at,
                            indexes: vec![i],
                        });
                    }
                },
                GatewayRecord::Seen { lift, at } => match seen_at.get(lift.as_str()) {
                    Some(&slot) => seen[slot].1 = seen[slot].1.max(*at),
                    None => {
                        seen_at.insert(lift, seen.len());
                        seen.push((lift, *at));
                    }
                },
                GatewayRecord::Token {
                    lift,
                    domain,
                    digest,
                    at,
                } => {
                    let row = TokenRow {
                        lift,
                        domain,
                        digest,
                        at: *at,
                    };
                    match token_at.get(&(lift.as_str(), domain.as_str())) {
                        Some(&slot) => tokens[slot] = row,
                        None => {
                            token_at.insert((lift, domain), tokens.len());
                            tokens.push(row);
                        }
                    }
                }
            }
        }
        RecordBatch {
            connected,
            seen,
            tokens,
        }
    }
}

/// The statement [`Store::gateway_rows`] asks `rows` CONNECTs about. Per CONNECT: the account
/// of its domain, the row of its lift in that account (its plain id, or the id scoped by the
/// account's name: column 4 is the id and the scope's separator), whether another account's
/// lift has the plain id, and whether users hold subscriptions of the lift (most hold none:
/// then they are not read at CONNACK).
///
/// Each candidate row (the plain key's, the scoped key's) is joined on its key, then the lift's
/// row on the key found. Joined on `id = plain OR id = scoped` instead, PostgreSQL's generic
/// plan for a full batch hashed the join on the domain and tested every lift of the account
/// against every CONNECT: 13 s a look-up with 100,000 lifts in one account
/// (docs/BENCHMARKS.md §First contact on a durable PostgreSQL).
fn lookup_sql(rows: usize) -> String {
    format!(
        "SELECT v.column1 AS i, a.name AS account, g.id AS key, \
         (SELECT COUNT(*) FROM (SELECT 1 FROM gateways WHERE id = v.column2 LIMIT 1) AS t) AS taken, \
         (SELECT COUNT(*) FROM (SELECT 1 FROM subscriptions WHERE lift = g.id LIMIT 1) AS s) AS subscribed, \
         g.token_hash, g.token_next, g.token_set, g.domain, g.boardhash \
         FROM (VALUES {}) AS v \
         LEFT JOIN accounts AS a ON a.domain = v.column3 \
         LEFT JOIN gateways AS gp ON gp.id = v.column2 AND gp.domain = v.column3 \
         LEFT JOIN gateways AS gs ON gs.id = v.column4 || a.name AND gs.domain = v.column3 \
         LEFT JOIN gateways AS g ON g.id = COALESCE(gp.id, gs.id)",
        parameter_rows(rows, 4)
    )
}

/// Make or refresh the rows of `rows` (one statement): the keys of those written, which are
/// all but those another account's row holds (its row is left as it is).
async fn upsert_rows(
    tx: &mut sqlx::Transaction<'_, sqlx::Any>,
    rows: &[ConnectedRow<'_>],
) -> Result<std::collections::HashSet<String>, sqlx::Error> {
    let sql = format!(
        "INSERT INTO gateways (id, vendorid, productcode, sernum, liftnum, hardware, software, boardhash, domain, api, last_seen) \
         VALUES {} \
         ON CONFLICT (id) DO UPDATE SET liftnum = excluded.liftnum, hardware = excluded.hardware, \
         software = excluded.software, boardhash = excluded.boardhash, api = excluded.api, \
         last_seen = CASE WHEN gateways.last_seen > excluded.last_seen THEN gateways.last_seen ELSE excluded.last_seen END \
         WHERE gateways.domain = excluded.domain \
         RETURNING id",
        parameter_rows(rows.len(), 11)
    );
    let mut query = sqlx::query(&sql);
    for row in rows {
        let identity = row.identity;
        query = query
            .bind(row.lift)
            .bind(i64::from(identity.vendorid))
            .bind(i64::from(identity.productcode))
            .bind(&identity.sernum)
            .bind(&identity.liftnum)
            .bind(&identity.hardware)
            .bind(&identity.software)
            .bind(&identity.boardhash)
            .bind(row.domain)
            .bind(i64::from(row.api))
            .bind(row.at);
    }
    let written = query.fetch_all(&mut **tx).await?;
    written.iter().map(|row| row.try_get("id")).collect()
}

impl Store {
    /// What the registry holds of each of `connects` (NXg §5.2, §5.4), in their order, read in
    /// one statement: a reconnect storm's admissions take a pooled connection and a round trip
    /// per batch instead of per gateway (docs/PORTAL.md §Stores). The decision is the portal's
    /// (`admissions::decide`), not the database's.
    pub async fn gateway_rows(&self, connects: &[&Connect]) -> Result<Vec<GatewayRow>, StoreError> {
        let Some(last) = connects.len().checked_sub(1) else {
            return Ok(Vec::new());
        };
        // Batches padded to a power of two (repeating the last CONNECT) make a few distinct
        // statements, each prepared once per connection, not one per batch size.
        let rows = connects.len().next_power_of_two();
        let sql = lookup_sql(rows);
        let mut query = sqlx::query(&sql);
        let ids: Vec<String> = connects.iter().map(|c| lift_id(&c.identity)).collect();
        for i in 0..rows {
            let at = i.min(last);
            query = query
                .bind(at as i64)
                .bind(&ids[at])
                .bind(&connects[at].domaintoken)
                .bind(cloud_types::lifts::scoped_key(&ids[at], ""));
        }
        let mut found: Vec<Option<GatewayRow>> = (0..connects.len()).map(|_| None).collect();
        for row in query.fetch_all(&self.pool).await? {
            let i = usize::try_from(row.try_get::<i64, _>("i")?).unwrap_or(usize::MAX);
            if let (Some(slot), Some(id)) = (found.get_mut(i), ids.get(i)) {
                *slot = Some(GatewayRow::from_row(&row, id)?);
            }
        }
        found
            .into_iter()
            .map(|row| row.ok_or_else(|| sqlx::Error::RowNotFound.into()))
            .collect()
    }

    /// Write `records` as if in order, in one transaction (a storm of reconnects costs one
    /// commit per batch, not one per gateway). `last_seen` only moves forward, so a record
    /// written late never takes it back.
    pub async fn record(&self, records: &[GatewayRecord]) -> Result<(), StoreError> {
        self.record_batch(records).await.map(drop)
    }

    /// [`Store::record`], in a statement per kind of record (and per 256 rows), not one per
    /// record: a fleet's first contacts cost the database a round trip per batch
    /// (docs/PORTAL.md §Stores). For each record, in order: whether its lift's row is its
    /// account's — false only for a [`GatewayRecord::Connected`] of a key another account's
    /// row holds (two first contacts of one identity from two accounts at once), which is left
    /// as it is.
    ///
    /// The records are grouped (rows made or refreshed, then last heard, then tokens) and
    /// those of one lift merged: each kind touches other columns, a row's identity is the last
    /// one given and `last_seen` the latest, so the rows end as the records one by one in order
    /// would leave them. A lift named by two accounts' records is written once per account, in
    /// the order they came, so the row's owner decides as it did.
    pub async fn record_batch(&self, records: &[GatewayRecord]) -> Result<Vec<bool>, StoreError> {
        let batches = RecordBatch::all(records);
        let mut conn = self.writer().await?;
        let outcome: Result<_, sqlx::Error> = async {
            let mut tx = sqlx::Connection::begin(&mut *conn).await?;
            let mut ours = vec![true; records.len()];
            for batch in &batches {
            for round in &batch.connected {
                for rows in crate::chunks_by_binary_digits(round, ROWS_PER_STATEMENT) {
                    let written = upsert_rows(&mut tx, rows).await?;
                    for row in rows {
                        if !written.contains(row.lift) {
                            for &i in &row.indexes {
                                ours[i] = false;
                            }
                        }
                    }
                }
            }
            for rows in crate::chunks_by_binary_digits(&batch.seen, ROWS_PER_STATEMENT) {
                let sql = format!(
                    "UPDATE gateways SET last_seen = v.column2 FROM (VALUES {}) AS v \
                     WHERE gateways.id = v.column1 AND gateways.last_seen < v.column2",
                    parameter_rows(rows.len(), 2)
                );
                let mut query = sqlx::query(&sql);
                for (lift, at) in rows {
                    query = query.bind(*lift).bind(*at);
                }
                query.execute(&mut *tx).await?;
            }
            for rows in crate::chunks_by_binary_digits(&batch.tokens, ROWS_PER_STATEMENT) {
                let sql = format!(
                    "UPDATE gateways SET token_hash = v.column3, token_set = v.column4, token_next = NULL \
                     FROM (VALUES {}) AS v WHERE gateways.id = v.column1 AND gateways.domain = v.column2",
                    parameter_rows(rows.len(), 4)
                );
                let mut query = sqlx::query(&sql);
                for row in rows {
                    query = query
                        .bind(row.lift)
                        .bind(row.domain)
                        .bind(row.digest)
                        .bind(row.at);
                }
                query.execute(&mut *tx).await?;
            }
            }
            tx.commit().await?;
            Ok(ours)
        }
        .await;
        self.settle(conn, outcome).await
    }

    /// The gateway of `lift` (of `domain`) confirmed `token` ([`GatewayRecord::Token`]),
    /// written at once.
    pub async fn set_token(&self, lift: &str, domain: &str, token: &str) -> Result<(), StoreError> {
        self.record(&[GatewayRecord::token(lift, domain, token)])
            .await
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
        let change = AuditedChange {
            statements: &[
                "UPDATE gateways SET token_hash = NULL, token_next = NULL, token_set = 0 WHERE id = $1 AND domain = $2",
            ],
            action: "token reset",
            object: "cloud token",
            new_value: "(none: first contact next)",
        };
        self.audited(change, domain, lift, by).await
    }

    /// The name of the account lift `lift` (a key) belongs to.
    pub async fn account_of(&self, lift: &str) -> Result<Option<String>, StoreError> {
        let row = sqlx::query(
            "SELECT a.name FROM gateways g JOIN accounts a ON a.domain = g.domain WHERE g.id = $1",
        )
        .bind(lift)
        .fetch_optional(&self.pool)
        .await?;
        Ok(row.map(|r| r.try_get("name")).transpose()?)
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

    /// One lift of `account`, by the id its operators see (or its key), if it has one.
    pub async fn lift(
        &self,
        account: &Account,
        id: &str,
    ) -> Result<Option<LiftRecord>, StoreError> {
        let [plain, scoped] = cloud_types::lifts::keys_of(id, &account.name);
        let row = sqlx::query("SELECT * FROM gateways WHERE (id = $1 OR id = $2) AND domain = $3")
            .bind(plain)
            .bind(scoped)
            .bind(&account.domain)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.as_ref().map(Store::lift_from).transpose()?)
    }

    /// Retire lift `lift` (a key) of `account` for `by`, audited: its row and everything
    /// stored of it — telemetry and its roll-ups, bus events, alarms, subscriptions, the
    /// elevation on record — go in one transaction, so its key may later be another
    /// account's lift without anything of this one. Its gateway's next CONNECT is a first
    /// contact. False when the account has no such lift.
    pub async fn retire(
        &self,
        account: &Account,
        lift: &str,
        by: &str,
    ) -> Result<bool, StoreError> {
        let change = AuditedChange {
            statements: &[
                "DELETE FROM gateways WHERE id = $1 AND domain = $2",
                "DELETE FROM telemetry WHERE lift = $1",
                "DELETE FROM telemetry_minute WHERE lift = $1",
                "DELETE FROM telemetry_hour WHERE lift = $1",
                "DELETE FROM lift_status WHERE lift = $1",
                "DELETE FROM events WHERE lift = $1",
                "DELETE FROM alarms WHERE lift = $1",
                "DELETE FROM subscriptions WHERE lift = $1",
                "DELETE FROM elevations WHERE lift = $1",
            ],
            action: "lift retired",
            object: "lift",
            new_value: "(removed with its data)",
        };
        self.audited(change, &account.domain, lift, by).await
    }

    /// Carry out `change` on lift `lift` of `domain` for `by` and write its audit entry, in one
    /// transaction: both or neither. False (nothing done) when its first statement, on the
    /// lift's row, finds none.
    async fn audited(
        &self,
        change: AuditedChange<'_>,
        domain: &str,
        lift: &str,
        by: &str,
    ) -> Result<bool, StoreError> {
        let mut conn = self.writer().await?;
        let outcome: Result<_, sqlx::Error> = async {
            let mut tx = sqlx::Connection::begin(&mut *conn).await?;
            for (n, statement) in change.statements.iter().enumerate() {
                let mut query = sqlx::query(statement).bind(lift);
                if statement.contains("$2") {
                    query = query.bind(domain);
                }
                let done = query.execute(&mut *tx).await?;
                if n == 0 && done.rows_affected() == 0 {
                    tx.rollback().await?;
                    return Ok(false);
                }
            }
            sqlx::query(
                "INSERT INTO audit (id, at, account, lift, action, object, old_value, new_value, result, owner) \
                 VALUES ($1, $2, $3, $4, $5, $6, NULL, $7, 'ok', (SELECT name FROM accounts WHERE domain = $8))",
            )
            .bind(crate::new_id())
            .bind(now_ms())
            .bind(by)
            .bind(lift)
            .bind(change.action)
            .bind(change.object)
            .bind(change.new_value)
            .bind(domain)
            .execute(&mut *tx)
            .await?;
            tx.commit().await?;
            Ok(true)
        }
        .await;
        self.settle(conn, outcome).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A record of lift `l` (of three) of account `d` (of two) at time `at`.
    fn record(kind: u8, l: u8, d: u8, at: i64) -> GatewayRecord {
        let lift = format!("1050-4096-L{l}");
        let domain = ["MAS", "OTH"][usize::from(d)].to_owned();
        match kind {
            0 => {
                let mut connect = testkit::connect(&format!("L{l}"), &domain, None);
                connect.identity.software = format!("v{at}");
                GatewayRecord::Connected {
                    lift,
                    identity: connect.identity,
                    domain,
                    api: 1,
                    at,
                }
            }
            1 => GatewayRecord::Seen { lift, at },
            _ => GatewayRecord::Token {
                lift,
                domain,
                digest: format!("digest {at}"),
                at,
            },
        }
    }

    async fn fresh(dir: &tempfile::TempDir, name: &str) -> Store {
        let url = format!("sqlite://{}", dir.path().join(name).display());
        let store = Store::open(&url).await.unwrap();
        store.add_account("masora", "MAS").await.unwrap();
        store.add_account("other", "OTH").await.unwrap();
        store
    }

    /// Every column of every row, in key order.
    async fn rows(store: &Store) -> Vec<String> {
        let rows = sqlx::query(
            "SELECT id, liftnum, software, domain, api, token_hash, token_set, token_next, last_seen \
             FROM gateways ORDER BY id",
        )
        .fetch_all(&store.pool)
        .await
        .unwrap();
        rows.iter()
            .map(|r| {
                format!(
                    "{} {} {} {} {} {:?} {} {:?} {}",
                    r.get::<String, _>("id"),
                    r.get::<String, _>("liftnum"),
                    r.get::<String, _>("software"),
                    r.get::<String, _>("domain"),
                    r.get::<i64, _>("api"),
                    r.get::<Option<String>, _>("token_hash"),
                    r.get::<i64, _>("token_set"),
                    r.get::<Option<String>, _>("token_next"),
                    r.get::<i64, _>("last_seen"),
                )
            })
            .collect()
    }

    /// `records` in one batch leave `batched` as they leave `one_by_one` written one at a
    /// time in order, and say of each whether the row is its account's as the one-by-one
    /// writes do.
    async fn a_batch_is_its_records_in_order(
        batched: &Store,
        one_by_one: &Store,
        records: &[GatewayRecord],
    ) {
        let ours = batched.record_batch(records).await.unwrap();
        let mut expected = Vec::new();
        for record in records {
            let alone = one_by_one
                .record_batch(std::slice::from_ref(record))
                .await
                .unwrap();
            expected.extend(alone);
        }
        assert_eq!(rows(batched).await, rows(one_by_one).await, "{records:#?}");
        assert_eq!(ours, expected, "{records:#?}");
    }

    /// The sequence that needs every rule: a lift first named by one account, then by the
    /// other, then by the first again; a token before and after its row; times out of order.
    fn crafted() -> Vec<GatewayRecord> {
        vec![
            record(2, 0, 0, 5),
            record(0, 0, 0, 10),
            record(0, 0, 1, 12),
            record(1, 0, 0, 30),
            record(0, 0, 0, 20),
            record(2, 0, 1, 40),
            record(2, 0, 0, 41),
            record(0, 1, 1, 50),
            record(1, 1, 0, 45),
            record(0, 1, 0, 60),
            record(2, 1, 0, 61),
            record(1, 2, 0, 65),
            record(0, 2, 0, 66),
            record(1, 2, 0, 70),
        ]
    }

    #[tokio::test]
    async fn sqlite_crafted() {
        let dir = tempfile::tempdir().unwrap();
        let (batched, one_by_one) = (fresh(&dir, "a.db").await, fresh(&dir, "b.db").await);
        a_batch_is_its_records_in_order(&batched, &one_by_one, &crafted()).await;
        // Again, on the rows the first left.
        a_batch_is_its_records_in_order(&batched, &one_by_one, &crafted()).await;
    }

    /// PostgreSQL refuses a statement that changes one row twice: the rounds keep a lift to
    /// one row of each statement.
    #[tokio::test]
    async fn postgres_crafted() {
        let (Some(a), Some(b)) = (
            testkit::postgres("batch_a").await,
            testkit::postgres("batch_b").await,
        ) else {
            return;
        };
        let open = |url: String| async move {
            let store = Store::open(&url).await.unwrap();
            store.add_account("masora", "MAS").await.unwrap();
            store.add_account("other", "OTH").await.unwrap();
            store
        };
        let (batched, one_by_one) = (open(a.to_string()).await, open(b.to_string()).await);
        a_batch_is_its_records_in_order(&batched, &one_by_one, &crafted()).await;
        a_batch_is_its_records_in_order(&batched, &one_by_one, &crafted()).await;
    }

    /// A full batch's look-up as PostgreSQL runs a prepared statement from its sixth execution
    /// on (its generic plan, forced here) finds each CONNECT's lift by its key: the rows its
    /// joins test and throw away stay fewer than the account's lifts, where testing every lift
    /// of the account against every CONNECT threw away 256 × 2,000 (what made a restarted
    /// portal's look-ups take 13 s with 100,000 lifts in one account).
    #[tokio::test]
    async fn postgres_lookup_reads_each_lift_by_its_key() {
        let Some(url) = testkit::postgres("lookup_plan").await else {
            return;
        };
        let store = Store::open(&url).await.unwrap();
        store.add_account("masora", "MAS").await.unwrap();
        let connects: Vec<Connect> = (0..2000)
            .map(|n| testkit::connect(&format!("L{n}"), "MAS", None))
            .collect();
        let records: Vec<GatewayRecord> = connects
            .iter()
            .map(|c| GatewayRecord::connected(&lift_id(&c.identity), c, 1))
            .collect();
        store.record_batch(&records).await.unwrap();
        sqlx::query("ANALYZE").execute(&store.pool).await.unwrap();
        let mut conn = store.pool.acquire().await.unwrap();
        let rows = 256;
        for statement in [
            "SET plan_cache_mode = force_generic_plan".to_owned(),
            format!("PREPARE lookup AS {}", lookup_sql(rows)),
        ] {
            sqlx::query(&statement).execute(&mut *conn).await.unwrap();
        }
        let arguments: Vec<String> = connects[..rows]
            .iter()
            .enumerate()
            .map(|(i, c)| {
                let id = lift_id(&c.identity);
                let scoped = cloud_types::lifts::scoped_key(&id, "");
                format!("'{i}', '{id}', 'MAS', '{scoped}'")
            })
            .collect();
        let plan: Vec<String> = sqlx::query_scalar(&format!(
            "EXPLAIN (ANALYZE, FORMAT TEXT) EXECUTE lookup({})",
            arguments.join(", ")
        ))
        .fetch_all(&mut *conn)
        .await
        .unwrap();
        let thrown_away: u64 = plan
            .iter()
            .filter_map(|line| line.split_once("Rows Removed by Join Filter: "))
            .filter_map(|(_, n)| n.trim().parse::<u64>().ok())
            .sum();
        assert!(
            thrown_away < 2000,
            "{thrown_away} rows thrown away:\n{}",
            plan.join("\n")
        );
        // And it found them: each CONNECT's row, once.
        let found = store
            .gateway_rows(&connects[..rows].iter().collect::<Vec<_>>())
            .await
            .unwrap();
        assert!(found.iter().all(|row| row.registered.is_some()));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]
        #[test]
        fn any_batch_is_its_records_in_order(
            first in prop::collection::vec((0u8..3, 0u8..3, 0u8..2, 0i64..100), 0..24),
            second in prop::collection::vec((0u8..3, 0u8..3, 0u8..2, 0i64..100), 0..24),
        ) {
            let runtime = tokio::runtime::Builder::new_current_thread()
                .enable_all()
                .build()
                .unwrap();
            runtime.block_on(async {
                let dir = tempfile::tempdir().unwrap();
                let (batched, one_by_one) = (fresh(&dir, "a.db").await, fresh(&dir, "b.db").await);
                for batch in [first, second] {
                    let records: Vec<_> =
                        batch.into_iter().map(|(k, l, d, at)| record(k, l, d, at)).collect();
                    a_batch_is_its_records_in_order(&batched, &one_by_one, &records).await;
                }
            });
        }
    }
}
