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
        let values = parameter_rows(rows, 4);
        // Per CONNECT: the account of its domain, the row of its lift in that account (its
        // plain id, or the id scoped by the account's name: column 4 is the id and the scope's
        // separator), whether another account's lift has the plain id, and whether users hold
        // subscriptions of the lift (most hold none: then they are not read at CONNACK).
        let sql = format!(
            "SELECT v.column1 AS i, a.name AS account, g.id AS key, \
             (SELECT COUNT(*) FROM (SELECT 1 FROM gateways WHERE id = v.column2 LIMIT 1) AS t) AS taken, \
             (SELECT COUNT(*) FROM (SELECT 1 FROM subscriptions WHERE lift = g.id LIMIT 1) AS s) AS subscribed, \
             g.token_hash, g.token_next, g.token_set, g.domain, g.boardhash \
             FROM (VALUES {values}) AS v \
             LEFT JOIN accounts AS a ON a.domain = v.column3 \
             LEFT JOIN gateways AS g ON g.domain = v.column3 AND (g.id = v.column2 OR g.id = v.column4 || a.name)"
        );
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

    /// Write `records` in order, in one transaction (a storm of reconnects costs one commit
    /// per batch, not one per gateway). `last_seen` only moves forward, so a record written
    /// late never takes it back.
    pub async fn record(&self, records: &[GatewayRecord]) -> Result<(), StoreError> {
        let mut conn = self.writer().await?;
        let outcome: Result<_, sqlx::Error> = async {
        let mut tx = sqlx::Connection::begin(&mut *conn).await?;
        for record in records {
            match record {
                GatewayRecord::Connected {
                    lift,
                    identity,
                    domain,
                    api,
                    at,
                } => {
                    // Another account's row of the key (two first contacts of one identity
                    // from two accounts at once) is left as it is: the admission checks whose
                    // row it is after writing (`Store::domain_of`).
                    sqlx::query(
                        "INSERT INTO gateways (id, vendorid, productcode, sernum, liftnum, hardware, software, boardhash, domain, api, token_hash, last_seen) \
                         VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9, $10, NULL, $11) \
                         ON CONFLICT (id) DO UPDATE SET liftnum = $5, hardware = $6, software = $7, boardhash = $8, api = $10, \
                         last_seen = CASE WHEN gateways.last_seen > $11 THEN gateways.last_seen ELSE $11 END \
                         WHERE gateways.domain = $9",
                    )
                    .bind(lift)
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
                GatewayRecord::Token {
                    lift,
                    domain,
                    digest,
                    at,
                } => {
                    sqlx::query(
                        "UPDATE gateways SET token_hash = $1, token_set = $2, token_next = NULL WHERE id = $3 AND domain = $4",
                    )
                    .bind(digest)
                    .bind(*at)
                    .bind(lift)
                    .bind(domain)
                    .execute(&mut *tx)
                    .await?;
                }
            }
        }
        tx.commit().await?;
        Ok(())
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

    /// The domain (account) a registered lift belongs to.
    pub async fn domain_of(&self, lift: &str) -> Result<Option<String>, StoreError> {
        let row = sqlx::query("SELECT domain FROM gateways WHERE id = $1")
            .bind(lift)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.map(|r| r.try_get("domain")).transpose()?)
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
