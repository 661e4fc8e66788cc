//! What lift insights read and keep (docs/PORTAL.md §Availability, §Trends): each lift's status
//! changes (a few a day, kept as long as the roll-ups), the EMCY faults raised in a period, a
//! counter's value at a moment, and the mean of a numeric object over a window.
//!
//! A report of a whole account asks a handful of statements, each answering for all its lifts
//! at once: per lift a search along an index for the period (`gateways g CROSS JOIN …` makes
//! SQLite take the account's lifts first), never a scan of the history of every lift.

use std::collections::{BTreeMap, HashMap};

use sqlx::Row;

use crate::{Store, StoreError};
use cloud_types::insights::Status;

/// One change of a lift's status.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StatusRow {
    /// The lift (its registry key).
    pub lift: String,
    /// From when (ms since the epoch).
    pub at: i64,
    /// What it became.
    pub status: Status,
}

/// A lift's statuses over a period: the one in force at its start, then each change inside it.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Timeline {
    /// In force at the period's start (none: nothing recorded before).
    pub before: Option<Status>,
    /// Changes after the start and before the end, oldest first.
    pub changes: Vec<(i64, Status)>,
}

/// A counter's values at a period's start and at its end, where known.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Edges {
    /// At the start.
    pub start: Option<f64>,
    /// At the end.
    pub end: Option<f64>,
}

/// Which lifts a report covers: those of an account's domain, or one of them.
#[derive(Debug, Clone, Copy)]
pub struct Lifts<'a> {
    /// The account's domain.
    pub domain: &'a str,
    /// Only this lift (its registry key).
    pub lift: Option<&'a str>,
}

impl<'a> Lifts<'a> {
    /// The `gateways` rows of these lifts, as `$1`/`$2` of a statement.
    const WHERE: &'static str = "g.domain = $1 AND ($2 = '' OR g.id = $2)";

    fn only(self) -> &'a str {
        self.lift.unwrap_or("")
    }
}

/// The statements a report runs, each for all the lifts of an account at once.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Statement {
    /// Each lift's status in force at the period's start and its changes inside the period
    /// (one row per lift: the changes in one text, which the database joins far faster than
    /// a row per change would be sent).
    Timelines,
    /// The faults raised in it.
    Faults,
    /// The counters' values at both edges of the period (as many counters as it holds).
    Counters(usize),
}

impl Statement {
    /// Every statement, in the order a report runs them.
    pub const ALL: [Statement; 3] = [
        Statement::Timelines,
        Statement::Faults,
        Statement::Counters(3),
    ];

    /// What it is called.
    pub fn name(self) -> &'static str {
        match self {
            Statement::Timelines => "statuses",
            Statement::Faults => "faults",
            Statement::Counters(_) => "counters at the edges",
        }
    }

    fn sql(self, postgres: bool) -> String {
        let lifts = Lifts::WHERE;
        let joined = if postgres {
            "string_agg"
        } else {
            "group_concat"
        };
        match self {
            // Each change as `MS STATUS`, its time counted from the period's start and its
            // status by the first two letters of its name: a third of the text.
            Statement::Timelines => format!(
                "SELECT g.id AS lift, \
                 (SELECT s.status FROM lift_status s WHERE s.lift = g.id AND s.at <= $3 ORDER BY s.at DESC LIMIT 1) AS status, \
                 (SELECT {joined}(CAST(s.at - $3 AS TEXT) || ' ' || substr(s.status, 1, 2), ',') FROM lift_status s \
                 WHERE s.lift = g.id AND s.at > $3 AND s.at < $4) AS changes \
                 FROM gateways g WHERE {lifts}"
            ),
            Statement::Faults => format!(
                "SELECT a.lift, a.code, COUNT(*) AS n FROM gateways g CROSS JOIN alarms a \
                 WHERE {lifts} AND a.lift = g.id AND a.kind = 'emcy' AND a.raised >= $3 AND a.raised < $4 \
                 GROUP BY a.lift, a.code"
            ),
            Statement::Counters(n) => {
                // Per counter and edge the last raw value at or before it, or where the raw
                // values are gone the last hour roll-up that ended by then ($5, $6).
                let at = |counter: usize, edge: usize| {
                    let m = 7 + counter;
                    format!(
                        "COALESCE(\
                         (SELECT t.value FROM telemetry t WHERE t.lift = g.id AND t.mplex = ${m} AND t.at <= ${e} ORDER BY t.at DESC LIMIT 1), \
                         (SELECT h.last FROM telemetry_hour h WHERE h.lift = g.id AND h.mplex = ${m} AND h.at <= ${h} ORDER BY h.at DESC LIMIT 1)) \
                         AS c{counter}_{edge}",
                        e = 3 + edge,
                        h = 5 + edge
                    )
                };
                let columns: Vec<String> = (0..n)
                    .flat_map(|c| [at(c, 0), at(c, 1)])
                    .collect();
                format!(
                    "SELECT g.id AS lift, {} FROM gateways g WHERE {lifts}",
                    columns.join(", ")
                )
            }
        }
    }
}

/// Two letters name a status in [`Statement::Timelines`]' answer.
#[cfg(test)]
#[test]
fn two_letters_name_a_status() {
    let prefixes: std::collections::HashSet<&str> =
        Status::ALL.iter().map(|s| &s.name()[..2]).collect();
    assert_eq!(prefixes.len(), Status::ALL.len());
}

/// `sql` with its parameters `$1`–`$4` bound: the lifts, then the period.
fn over<'q>(
    sql: &'q str,
    lifts: Lifts<'q>,
    from: i64,
    to: i64,
) -> sqlx::query::Query<'q, sqlx::Any, sqlx::any::AnyArguments<'q>> {
    sqlx::query(sql)
        .bind(lifts.domain)
        .bind(lifts.only())
        .bind(from)
        .bind(to)
}

fn status_of(name: &str) -> Result<Status, sqlx::Error> {
    Status::from_name(name).ok_or_else(|| sqlx::Error::Decode(format!("status {name:?}").into()))
}

impl Store {
    /// `statement` in this database's dialect.
    fn sql(&self, statement: Statement) -> String {
        statement.sql(self.copy.is_some())
    }

    /// Each lift's [`Timeline`] from `from` to `to` (ms; `from` included, `to` excluded): every
    /// lift of `lifts`, also one without a status recorded.
    pub async fn timelines(
        &self,
        lifts: Lifts<'_>,
        from: i64,
        to: i64,
    ) -> Result<HashMap<String, Timeline>, StoreError> {
        let mut out: HashMap<String, Timeline> = HashMap::new();
        let sql = self.sql(Statement::Timelines);
        for r in over(&sql, lifts, from, to).fetch_all(&self.pool).await? {
            let before: Option<String> = r.try_get("status")?;
            let changes: Option<String> = r.try_get("changes")?;
            let mut changes = changes
                .iter()
                .flat_map(|c| c.split(','))
                .map(|change| {
                    let bad = || sqlx::Error::Decode(format!("status change {change:?}").into());
                    let (after, status) = change.split_once(' ').ok_or_else(bad)?;
                    let after: i64 = after.parse().map_err(|_| bad())?;
                    let status = Status::ALL
                        .into_iter()
                        .find(|s| status.len() == 2 && s.name().starts_with(status))
                        .ok_or_else(bad)?;
                    Ok((from + after, status))
                })
                .collect::<Result<Vec<_>, sqlx::Error>>()?;
            // Joined in no particular order (asking the database for one costs it a sort).
            changes.sort_by_key(|c: &(i64, Status)| c.0);
            out.insert(
                r.try_get("lift")?,
                Timeline {
                    before: before.as_deref().map(status_of).transpose()?,
                    changes,
                },
            );
        }
        Ok(out)
    }

    /// EMCY faults raised from `from` to `to` (ms, `to` excluded): per lift, per error code.
    pub async fn faults(
        &self,
        lifts: Lifts<'_>,
        from: i64,
        to: i64,
    ) -> Result<HashMap<String, BTreeMap<String, u64>>, StoreError> {
        let mut out: HashMap<String, BTreeMap<String, u64>> = HashMap::new();
        let sql = self.sql(Statement::Faults);
        for r in over(&sql, lifts, from, to).fetch_all(&self.pool).await? {
            let n: i64 = r.try_get("n")?;
            out.entry(r.try_get("lift")?)
                .or_default()
                .insert(r.try_get("code")?, u64::try_from(n).unwrap_or(0));
        }
        Ok(out)
    }

    /// Each lift's values of the counters `mplexes` at `from` and at `to` (ms): the last one
    /// stored at or before each — from the raw values, or where those are gone (`[database]
    /// telemetry_days`) from the last hour roll-up that ended by then; none where there is no
    /// number.
    pub async fn counters_at(
        &self,
        lifts: Lifts<'_>,
        mplexes: &[&str],
        from: i64,
        to: i64,
    ) -> Result<HashMap<String, Vec<Edges>>, StoreError> {
        let sql = self.sql(Statement::Counters(mplexes.len()));
        let mut query = over(&sql, lifts, from, to)
            .bind(from.saturating_sub(3_600_000))
            .bind(to.saturating_sub(3_600_000));
        for mplex in mplexes {
            query = query.bind(*mplex);
        }
        let number = |text: Option<String>| {
            text.and_then(|v| v.trim().parse::<f64>().ok())
                .filter(|v| v.is_finite())
        };
        let mut out = HashMap::new();
        for r in query.fetch_all(&self.pool).await? {
            let edges = (0..mplexes.len())
                .map(|c| {
                    Ok(Edges {
                        start: number(r.try_get(format!("c{c}_0").as_str())?),
                        end: number(r.try_get(format!("c{c}_1").as_str())?),
                    })
                })
                .collect::<Result<_, sqlx::Error>>()?;
            out.insert(r.try_get("lift")?, edges);
        }
        Ok(out)
    }

    /// Per lift, the mean of the numeric values of `mplex` stored from `from` to `to` (ms,
    /// `to` excluded) and how many there were; lifts without one are left out. Each lift's
    /// values are read along its index; values that are not numbers are passed over.
    pub async fn means(
        &self,
        mplex: &str,
        from: i64,
        to: i64,
    ) -> Result<HashMap<String, (f64, u64)>, StoreError> {
        // Casting text that is no number fails on PostgreSQL and yields 0 on SQLite: only a
        // number as JSON writes one (what gateways send for numeric objects) is cast.
        let number = if self.copy.is_some() {
            r"t.value ~ '^\s*-?(0|[1-9][0-9]*)(\.[0-9]+)?([eE][-+]?[0-9]+)?\s*$'"
        } else {
            "(CASE WHEN json_valid(trim(t.value)) THEN json_type(trim(t.value)) END) IN ('integer', 'real')"
        };
        // One pass over the window's values per lift, along its index (the gateways first).
        let sql = format!(
            "SELECT t.lift, AVG(CAST(t.value AS DOUBLE PRECISION)) AS mean, COUNT(*) AS n \
             FROM gateways g CROSS JOIN telemetry t \
             WHERE t.lift = g.id AND t.mplex = $1 AND t.at >= $2 AND t.at < $3 AND {number} \
             GROUP BY t.lift"
        );
        let mut out = HashMap::new();
        for r in sqlx::query(&sql)
            .bind(mplex)
            .bind(from)
            .bind(to)
            .fetch_all(&self.pool)
            .await?
        {
            let mean: Option<f64> = r.try_get("mean")?;
            let n: i64 = r.try_get("n")?;
            if let Some(mean) = mean.filter(|m| m.is_finite()) {
                out.insert(r.try_get("lift")?, (mean, n as u64));
            }
        }
        Ok(out)
    }

    /// The database's plan for `statement` over `lifts` (SQLite's `EXPLAIN QUERY PLAN`,
    /// PostgreSQL's `EXPLAIN`), one step a line: what a report's cost rests on.
    pub async fn explain(
        &self,
        statement: Statement,
        lifts: Lifts<'_>,
    ) -> Result<String, StoreError> {
        let postgres = self.copy.is_some();
        let prefix = if postgres {
            "EXPLAIN"
        } else {
            "EXPLAIN QUERY PLAN"
        };
        let sql = format!("{prefix} {}", self.sql(statement));
        let query = sqlx::query(&sql).bind(lifts.domain).bind(lifts.only());
        let query = match statement {
            Statement::Timelines | Statement::Faults => query.bind(0i64).bind(1i64),
            Statement::Counters(n) => {
                let mut query = query.bind(0i64).bind(1i64).bind(0i64).bind(1i64);
                for _ in 0..n {
                    query = query.bind("0x652001");
                }
                query
            }
        };
        let column = if postgres { "QUERY PLAN" } else { "detail" };
        let lines = query
            .fetch_all(&self.pool)
            .await?
            .iter()
            .map(|r| r.try_get::<String, _>(column))
            .collect::<Result<Vec<_>, _>>()?;
        Ok(lines.join("\n"))
    }

    /// Delete status changes older than `before` (ms), but each lift's last one before it (it
    /// still says what the lift was doing afterwards).
    pub async fn forget_statuses(&self, before: i64) -> Result<u64, StoreError> {
        let done = sqlx::query(
            "DELETE FROM lift_status WHERE at < $1 AND at < (SELECT MAX(l.at) FROM lift_status l \
             WHERE l.lift = lift_status.lift AND l.at < $1)",
        )
        .bind(before)
        .execute(&self.pool)
        .await?;
        Ok(done.rows_affected())
    }
}

/// Insert `rows` within a transaction (the alarm service writes them with its batch).
pub(crate) async fn insert(
    tx: &mut sqlx::AnyConnection,
    rows: &[StatusRow],
) -> Result<(), sqlx::Error> {
    for chunk in rows.chunks(100) {
        let sql = format!(
            "INSERT INTO lift_status (lift, at, status) VALUES {}",
            crate::parameter_rows(chunk.len(), 3)
        );
        let mut query = sqlx::query(&sql);
        for row in chunk {
            query = query.bind(&row.lift).bind(row.at).bind(row.status.name());
        }
        query.execute(&mut *tx).await?;
    }
    Ok(())
}
