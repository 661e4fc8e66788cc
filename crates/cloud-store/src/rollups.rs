//! Roll-ups of pushed values per object, per minute and per hour (docs/PORTAL.md §History):
//! each the smallest and largest number, the last value and how many came. A chart of a day or
//! a week reads them instead of millions of raw rows.
//!
//! They are made behind the writers, not by them ([`Store::roll_up`], once a minute): the
//! minutes that ended (with a lag for batches still on their way) are read back from the raw
//! rows and their minute rows replaced, then merged into their hours. Storing a value costs
//! nothing more; a minute rolled up again (values that arrived late, [`Store::rewind_roll_ups`])
//! is replaced, not added to, and its hours are made again from their minutes.

use std::collections::{BTreeSet, HashMap};
use std::sync::atomic::Ordering;

use futures_util::TryStreamExt;
use sqlx::Row;

use crate::{Store, StoreError};

/// How finely values are rolled up.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Grain {
    /// Per minute.
    Minute,
    /// Per hour.
    Hour,
}

impl Grain {
    /// Its length in ms.
    pub fn ms(self) -> i64 {
        match self {
            Grain::Minute => 60_000,
            Grain::Hour => 3_600_000,
        }
    }

    fn table(self) -> &'static str {
        match self {
            Grain::Minute => "telemetry_minute",
            Grain::Hour => "telemetry_hour",
        }
    }

    /// The start of the period `at` is in.
    pub fn floor(self, at: i64) -> i64 {
        at.saturating_sub(at.rem_euclid(self.ms()))
    }

    /// The start of the first period that begins at or after `at`.
    pub fn ceil(self, at: i64) -> i64 {
        let floor = self.floor(at);
        if floor == at {
            at
        } else {
            floor.saturating_add(self.ms())
        }
    }
}

/// An object's values over a period: the smallest and largest of those that are numbers, the
/// last one (and when it came), how many.
#[derive(Debug, Clone, PartialEq)]
pub struct Bucket {
    /// The period's start (ms since the epoch).
    pub at: i64,
    /// The smallest number (none when no value was a number).
    pub min: Option<f64>,
    /// The largest number.
    pub max: Option<f64>,
    /// The last value in text form.
    pub last: String,
    /// When the last value came.
    pub last_at: i64,
    /// How many values came.
    pub count: i64,
}

impl Bucket {
    /// A bucket of period `at` holding one value `value` that came at `value_at`.
    pub fn of(at: i64, value_at: i64, value: &str) -> Bucket {
        let number = value.trim().parse::<f64>().ok().filter(|v| v.is_finite());
        Bucket {
            at,
            min: number,
            max: number,
            last: value.to_owned(),
            last_at: value_at,
            count: 1,
        }
    }

    /// Take `other`'s values in too.
    pub fn merge(&mut self, other: &Bucket) {
        let pick = |a: Option<f64>, b: Option<f64>, f: fn(f64, f64) -> f64| match (a, b) {
            (Some(a), Some(b)) => Some(f(a, b)),
            (a, b) => a.or(b),
        };
        self.min = pick(self.min, other.min, f64::min);
        self.max = pick(self.max, other.max, f64::max);
        if other.last_at >= self.last_at {
            self.last.clone_from(&other.last);
            self.last_at = other.last_at;
        }
        self.count += other.count;
    }
}

/// Buckets by lift, object and period start, as they are gathered.
type Gathered = HashMap<(String, String, i64), Bucket>;

fn gather(into: &mut Gathered, grain: Grain, lift: String, mplex: String, bucket: Bucket) {
    let start = grain.floor(bucket.at);
    match into.entry((lift, mplex, start)) {
        std::collections::hash_map::Entry::Occupied(mut e) => e.get_mut().merge(&bucket),
        std::collections::hash_map::Entry::Vacant(e) => {
            e.insert(Bucket {
                at: start,
                ..bucket
            });
        }
    }
}

/// How far behind now the minutes are rolled up: batches of values still on their way (the
/// writers' 200 ms, a database that was slow) find their minute not yet rolled.
pub const LAG_MS: i64 = 90_000;

/// Minutes rolled up at once at most (a portal catching up after a pause goes on next time).
const MOST_MINUTES: i64 = 60;

/// What one round of [`Store::roll_up`] did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RolledUp {
    /// Raw values read.
    pub values: u64,
    /// Minute rows written.
    pub minutes: u64,
    /// Hour rows written.
    pub hours: u64,
}

impl Store {
    /// Until when (ms) every minute is rolled up.
    pub async fn rolled_up_to(&self) -> Result<Option<i64>, StoreError> {
        Ok(sqlx::query("SELECT done FROM rollup_state WHERE id = 1")
            .fetch_optional(&self.pool)
            .await?
            .map(|r| r.try_get::<i64, _>("done"))
            .transpose()?)
    }

    async fn set_rolled_up_to(&self, done: i64) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO rollup_state (id, done) VALUES (1, $1) ON CONFLICT (id) DO UPDATE SET done = $1",
        )
        .bind(done)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Values that came at `at` (ms) or later were stored late, after their minute may have
    /// been rolled up: roll up from there again.
    pub fn rewind_roll_ups(&self, at: i64) {
        self.rewind.fetch_min(at, Ordering::Relaxed);
    }

    /// Roll up the minutes that ended by `now` less [`LAG_MS`] (at most an hour of them per
    /// round), and the hours they are in; nothing while another process of a cluster does
    /// (its round reads the same minutes: two at once merged them into their hours twice).
    pub async fn roll_up(&self, now: i64) -> Result<RolledUp, StoreError> {
        let Some(turn) = self.turn("roll-up").await? else {
            return Ok(RolledUp::default());
        };
        let rolled = self.roll_up_round(now).await;
        turn.end().await;
        rolled
    }

    async fn roll_up_round(&self, now: i64) -> Result<RolledUp, StoreError> {
        let minute = Grain::Minute;
        let end_now = minute.floor(now - LAG_MS);
        let rewind = self.rewind.swap(i64::MAX, Ordering::Relaxed);
        let done = match self.rolled_up_to().await? {
            Some(done) => done,
            // A new database: from the oldest value kept (or now).
            None => sqlx::query("SELECT MIN(at) AS first FROM telemetry")
                .fetch_one(&self.pool)
                .await?
                .try_get::<Option<i64>, _>("first")?
                .map_or(end_now, |first| minute.floor(first)),
        };
        // From the first value on: a stretch without values (a new database's start, a quiet
        // night of a small fleet) is not walked through minute by minute.
        let first: Option<i64> =
            sqlx::query("SELECT MIN(at) AS first FROM telemetry WHERE at >= $1 AND at < $2")
                .bind(done.min(minute.floor(rewind)))
                .bind(end_now)
                .fetch_one(&self.pool)
                .await?
                .try_get("first")?;
        let Some(first) = first else {
            if end_now > done {
                self.set_rolled_up_to(end_now).await?;
            }
            return Ok(RolledUp::default());
        };
        let start = minute.floor(first);
        let end = end_now.min(start + MOST_MINUTES * minute.ms());
        if end <= start {
            // Nothing ended; a rewind not reached yet stays for the next round.
            if rewind < i64::MAX && minute.floor(rewind) >= end_now {
                self.rewind_roll_ups(rewind);
            }
            return Ok(RolledUp::default());
        }
        let mut minutes: Gathered = HashMap::new();
        let mut values = 0u64;
        let mut rows =
            sqlx::query("SELECT lift, mplex, value, at FROM telemetry WHERE at >= $1 AND at < $2")
                .bind(start)
                .bind(end)
                .fetch(&self.pool);
        while let Some(row) = rows.try_next().await? {
            let at: i64 = row.try_get("at")?;
            let value: String = row.try_get("value")?;
            values += 1;
            gather(
                &mut minutes,
                minute,
                row.try_get("lift")?,
                row.try_get("mplex")?,
                Bucket::of(at, at, &value),
            );
        }
        drop(rows);
        // Minutes before `done` were rolled up before: theirs are replaced, and their hours
        // made again from their minutes; new minutes are merged into their hours.
        let rolled_before: BTreeSet<i64> = (start..done.min(end))
            .step_by(usize::try_from(minute.ms()).unwrap_or(60_000))
            .map(|m| Grain::Hour.floor(m))
            .collect();
        let mut hours: Gathered = HashMap::new();
        for ((lift, mplex, at), bucket) in &minutes {
            if *at >= done {
                gather(
                    &mut hours,
                    Grain::Hour,
                    lift.clone(),
                    mplex.clone(),
                    bucket.clone(),
                );
            }
        }
        let mut conn = self.writer().await?;
        let outcome: Result<_, sqlx::Error> = async {
            let mut tx = sqlx::Connection::begin(&mut *conn).await?;
            if start < done {
                sqlx::query("DELETE FROM telemetry_minute WHERE at >= $1 AND at < $2")
                    .bind(start)
                    .bind(done.min(end))
                    .execute(&mut *tx)
                    .await?;
            }
            let written_minutes = write(&mut tx, minute, &minutes, Write::Replace).await?;
            let mut written_hours = write(&mut tx, Grain::Hour, &hours, Write::Merge).await?;
            for hour in rolled_before {
                written_hours += remake_hour(&mut tx, hour).await?;
            }
            sqlx::query(
                "INSERT INTO rollup_state (id, done) VALUES (1, $1) ON CONFLICT (id) DO UPDATE SET done = $1",
            )
            .bind(end.max(done))
            .execute(&mut *tx)
            .await?;
            tx.commit().await?;
            Ok(RolledUp {
                values,
                minutes: written_minutes,
                hours: written_hours,
            })
        }
        .await;
        let outcome = self.settle(conn, outcome).await;
        if outcome.is_err() && rewind < i64::MAX {
            self.rewind_roll_ups(rewind);
        }
        outcome
    }

    /// The roll-ups of `grain` of one object from `from` to before `to` (ms), oldest first.
    pub async fn roll_ups(
        &self,
        grain: Grain,
        lift: &str,
        mplex: &str,
        from: i64,
        to: i64,
    ) -> Result<Vec<Bucket>, StoreError> {
        let sql = format!(
            "SELECT at, min, max, last, last_at, count FROM {} WHERE lift = $1 AND mplex = $2 AND at >= $3 AND at < $4 ORDER BY at",
            grain.table()
        );
        let rows = sqlx::query(&sql)
            .bind(lift)
            .bind(mplex)
            .bind(from)
            .bind(to)
            .fetch_all(&self.pool)
            .await?;
        rows.iter()
            .map(bucket_of)
            .collect::<Result<_, _>>()
            .map_err(StoreError::from)
    }

    /// Delete roll-ups older than `before` (ms); how many went.
    pub async fn forget_roll_ups(&self, before: i64) -> Result<u64, StoreError> {
        let mut gone = 0;
        for grain in [Grain::Minute, Grain::Hour] {
            let sql = format!("DELETE FROM {} WHERE at < $1", grain.table());
            gone += sqlx::query(&sql)
                .bind(before)
                .execute(&self.pool)
                .await?
                .rows_affected();
        }
        Ok(gone)
    }
}

fn bucket_of(r: &sqlx::any::AnyRow) -> Result<Bucket, sqlx::Error> {
    Ok(Bucket {
        at: r.try_get("at")?,
        min: r.try_get("min")?,
        max: r.try_get("max")?,
        last: r.try_get("last")?,
        last_at: r.try_get("last_at")?,
        count: r.try_get("count")?,
    })
}

/// How a written roll-up meets one already there.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Write {
    /// It replaces it (a minute made again from all its values).
    Replace,
    /// Its values are added to it (an hour taking in new minutes).
    Merge,
}

/// Write `rows` into `grain`'s table; how many.
async fn write(
    conn: &mut sqlx::AnyConnection,
    grain: Grain,
    rows: &Gathered,
    how: Write,
) -> Result<u64, sqlx::Error> {
    let table = grain.table();
    let update = match how {
        Write::Replace => "min = excluded.min, max = excluded.max, last = excluded.last, \
                           last_at = excluded.last_at, count = excluded.count"
            .to_owned(),
        // Portable: SQLite's two-argument min() is NULL when either is, PostgreSQL has LEAST.
        Write::Merge => format!(
            "min = CASE WHEN excluded.min IS NULL THEN {t}.min WHEN {t}.min IS NULL OR excluded.min < {t}.min THEN excluded.min ELSE {t}.min END, \
             max = CASE WHEN excluded.max IS NULL THEN {t}.max WHEN {t}.max IS NULL OR excluded.max > {t}.max THEN excluded.max ELSE {t}.max END, \
             last = CASE WHEN excluded.last_at >= {t}.last_at THEN excluded.last ELSE {t}.last END, \
             last_at = CASE WHEN excluded.last_at >= {t}.last_at THEN excluded.last_at ELSE {t}.last_at END, \
             count = {t}.count + excluded.count",
            t = table
        ),
    };
    let rows: Vec<_> = rows.iter().collect();
    for chunk in rows.chunks(256) {
        let sql = format!(
            "INSERT INTO {table} (lift, mplex, at, min, max, last, last_at, count) VALUES {} \
             ON CONFLICT (lift, mplex, at) DO UPDATE SET {update}",
            crate::parameter_rows(chunk.len(), 8)
        );
        let mut query = sqlx::query(&sql);
        for ((lift, mplex, _), b) in chunk {
            query = query
                .bind(lift)
                .bind(mplex)
                .bind(b.at)
                .bind(b.min)
                .bind(b.max)
                .bind(&b.last)
                .bind(b.last_at)
                .bind(b.count);
        }
        query.execute(&mut *conn).await?;
    }
    Ok(rows.len() as u64)
}

/// Make the hour starting at `hour` again from its minutes; how many hour rows.
async fn remake_hour(conn: &mut sqlx::AnyConnection, hour: i64) -> Result<u64, sqlx::Error> {
    let rows = sqlx::query(
        "SELECT lift, mplex, at, min, max, last, last_at, count FROM telemetry_minute WHERE at >= $1 AND at < $2",
    )
    .bind(hour)
    .bind(hour + Grain::Hour.ms())
    .fetch_all(&mut *conn)
    .await?;
    let mut hours: Gathered = HashMap::new();
    for r in &rows {
        gather(
            &mut hours,
            Grain::Hour,
            r.try_get("lift")?,
            r.try_get("mplex")?,
            bucket_of(r)?,
        );
    }
    sqlx::query("DELETE FROM telemetry_hour WHERE at = $1")
        .bind(hour)
        .execute(&mut *conn)
        .await?;
    write(conn, Grain::Hour, &hours, Write::Replace).await
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::TelemetryRow;

    /// Four stores on one PostgreSQL are four processes of a cluster, each rolling up once a
    /// minute: started together, every value is still read once and counted once in its
    /// minute and its hour (without turns, the rounds merged the same minutes into the hours
    /// up to four times, or deadlocked).
    #[tokio::test]
    async fn a_cluster_rolls_each_value_up_once() {
        let Some(url) = testkit::postgres("rollup_turns").await else {
            return;
        };
        let stores =
            futures_util::future::try_join_all((0..4).map(|_| Store::open_pooled(&url, 4)))
                .await
                .unwrap();
        // An hour's values of 20 lifts, one a second: one round's worth.
        let hour = 1_700_000_000_000i64 - 1_700_000_000_000i64 % 3_600_000;
        let rows: Vec<TelemetryRow> = (0..20)
            .flat_map(|lift| {
                (0..3_600).map(move |s| TelemetryRow {
                    lift: format!("1050-4096-ROLL-{lift:02}"),
                    mplex: "0x638301".into(),
                    node: 0,
                    value: (s % 50).to_string(),
                    at: hour + s * 1_000,
                })
            })
            .collect();
        for chunk in rows.chunks(10_000) {
            stores[0].telemetry(chunk).await.unwrap();
        }
        let now = hour + 3_600_000 + LAG_MS;
        let start = std::sync::Arc::new(tokio::sync::Barrier::new(stores.len()));
        let rounds = futures_util::future::join_all(stores.iter().map(|store| {
            let start = start.clone();
            async move {
                start.wait().await;
                store.roll_up(now).await
            }
        }))
        .await;
        let read: u64 = rounds.iter().map(|r| r.as_ref().unwrap().values).sum();
        assert_eq!(
            read,
            rows.len() as u64,
            "each value read by one round: {rounds:?}"
        );
        for lift in ["1050-4096-ROLL-00", "1050-4096-ROLL-19"] {
            for (grain, buckets) in [(Grain::Minute, 60), (Grain::Hour, 1)] {
                let rolled = stores[3]
                    .roll_ups(grain, lift, "0x638301", hour, hour + 3_600_000)
                    .await
                    .unwrap();
                assert_eq!(rolled.len(), buckets, "{grain:?}");
                let counted: i64 = rolled.iter().map(|b| b.count).sum();
                assert_eq!(counted, 3_600, "{lift} {grain:?}: each value counted once");
            }
        }
    }
}
