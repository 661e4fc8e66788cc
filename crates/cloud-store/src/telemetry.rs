//! Pushed values (telemetry): stored in batches, read back as history and as the newest
//! value of each object, deleted after the retention time.

use std::collections::HashMap;

use sqlx::postgres::PgPoolCopyExt;
use sqlx::Row;

use crate::{Store, StoreError};

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

impl Store {
    /// Store pushed values, all or none: on PostgreSQL by one binary `COPY`, on SQLite by
    /// multi-row INSERTs in one transaction.
    pub async fn telemetry(&self, batch: &[TelemetryRow]) -> Result<(), StoreError> {
        if let Some(pg) = &self.copy {
            let copied = async {
                let mut copy = pg
                    .copy_in_raw(
                        "COPY telemetry (lift, mplex, node, value, at) FROM STDIN (FORMAT binary)",
                    )
                    .await?;
                copy.send(copy_binary(batch)).await?;
                copy.finish().await
            }
            .await
            .map(|_| ())
            .map_err(StoreError::from);
            self.health().note(&copied);
            return copied;
        }
        // SQLite: multi-row INSERTs of 512 rows (2,560 parameters: far within SQLite's 32,766)
        // and the rest in chunks of 256, 128, … 1 by its binary digits: sqlx keeps each
        // statement prepared per connection, and ten sizes are at most ten statements (a
        // remainder of any length had been one more, each a VM of tens of KiB, up to sqlx's
        // 100 per connection). Anonymous parameters, because sqlx looks every numbered one up
        // by name, a linear search in SQLite: quadratic per statement.
        let mut conn = self.writer().await?;
        let outcome: Result<_, sqlx::Error> = async {
            let mut tx = sqlx::Connection::begin(&mut *conn).await?;
            for rows in crate::chunks_by_binary_digits(batch, 512) {
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
        .await;
        self.settle(conn, outcome).await
    }

    /// Stored values of one object from `from` to `to` (ms, both included), oldest first: (at,
    /// value); the first `limit` of them (a caller that must know whether there were more asks
    /// for one more).
    pub async fn values(
        &self,
        lift: &str,
        mplex: &str,
        from: i64,
        to: i64,
        limit: usize,
    ) -> Result<Vec<(i64, String)>, StoreError> {
        let rows = sqlx::query(
            "SELECT at, value FROM telemetry WHERE lift = $1 AND mplex = $2 AND at >= $3 AND at <= $4 ORDER BY at LIMIT $5",
        )
        .bind(lift)
        .bind(mplex)
        .bind(from)
        .bind(to)
        .bind(i64::try_from(limit).unwrap_or(i64::MAX))
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

    /// How many values are stored.
    pub async fn count_telemetry(&self) -> Result<i64, StoreError> {
        Ok(sqlx::query("SELECT COUNT(*) AS n FROM telemetry")
            .fetch_one(&self.pool)
            .await?
            .try_get("n")?)
    }

    /// Delete telemetry older than `before` (ms); how many values went.
    pub async fn forget_telemetry(&self, before: i64) -> Result<u64, StoreError> {
        let done = sqlx::query("DELETE FROM telemetry WHERE at < $1")
            .bind(before)
            .execute(&self.pool)
            .await?;
        Ok(done.rows_affected())
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
