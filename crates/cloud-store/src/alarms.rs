//! Bus events, alarms and the webhook outbox in the store (docs/PORTAL.md §Alarms).

use std::collections::HashMap;

use rand::Rng;
use sqlx::any::AnyRow;
use sqlx::Row;

use super::{Store, StoreError};
use cloud_types::alarms::{Acknowledgement, Alarm, Condition, Kind, Place, Severity};

/// A new id for an alarm or an outbox entry: random below 2⁵³ (exact in JSON numbers, no
/// coordination between portal processes).
pub fn new_id() -> i64 {
    rand::rng().random_range(1..(1i64 << 53))
}

/// One bus event to keep.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct EventRow {
    /// The lift.
    pub lift: String,
    /// When it happened (ms since the epoch).
    pub at: i64,
    /// `emcy`, `state` or `bus`.
    pub kind: String,
    /// The event as the gateway wrote it (JSON).
    pub body: String,
}

/// A webhook notification waiting for delivery.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OutboxEntry {
    /// Its id.
    pub id: i64,
    /// The receiver.
    pub url: String,
    /// The JSON body.
    pub body: String,
    /// The lift (for the audit).
    pub lift: String,
    /// Attempts so far.
    pub attempts: u32,
    /// When it was queued (ms).
    pub created: i64,
}

/// Each active alarm's condition and id.
fn conditions(rows: &[AnyRow]) -> Result<Vec<(Condition, i64)>, StoreError> {
    rows.iter()
        .map(|r| {
            let a = alarm_from(r)?;
            Ok((
                Condition {
                    lift: a.lift,
                    kind: a.kind,
                    place: a.node,
                    code: a.code,
                },
                a.id,
            ))
        })
        .collect::<Result<_, sqlx::Error>>()
        .map_err(StoreError::from)
}

fn alarm_from(r: &AnyRow) -> Result<Alarm, sqlx::Error> {
    let time = |ms: i64| nxg::msg::format_time(ms);
    let kind: String = r.try_get("kind")?;
    let severity: String = r.try_get("severity")?;
    let node: i64 = r.try_get("node")?;
    let net: i64 = r.try_get("net")?;
    let ack_by: Option<String> = r.try_get("ack_by")?;
    let ack_at: Option<i64> = r.try_get("ack_at")?;
    let ack_comment: Option<String> = r.try_get("ack_comment")?;
    let kind = Kind::from_name(&kind)
        .ok_or_else(|| sqlx::Error::Decode(format!("alarm kind {kind:?}").into()))?;
    Ok(Alarm {
        id: r.try_get("id")?,
        lift: r.try_get("lift")?,
        node: (!kind.is_lift_wide()).then(|| Place {
            id: u8::try_from(node).ok().filter(|n| *n > 0),
            net: u8::try_from(net).unwrap_or(1),
        }),
        kind,
        code: r.try_get("code")?,
        severity: Severity::from_name(&severity).unwrap_or(Severity::Major),
        text: r.try_get("text")?,
        raised: time(r.try_get("raised")?),
        acknowledged: match (ack_by, ack_at) {
            (Some(by), Some(at)) => Some(Acknowledgement {
                by,
                at: time(at),
                comment: ack_comment.unwrap_or_default(),
            }),
            _ => None,
        },
        cleared: r.try_get::<Option<i64>, _>("cleared")?.map(time),
    })
}

/// Which alarms a listing shows.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct AlarmFilter {
    /// Only those whose condition still holds.
    pub active: bool,
    /// Only this lift's.
    pub lift: Option<String>,
    /// At most this many, newest first.
    pub limit: u32,
}

impl Store {
    /// Write what the alarm service gathered, in one transaction: bus events, lifts' status
    /// changes, alarms raised, alarms cleared (id, when). Returns the cleared alarms as stored (with their
    /// acknowledgement, if any).
    pub async fn write_alarm_batch(
        &self,
        events: &[EventRow],
        statuses: &[crate::StatusRow],
        raised: &[Alarm],
        cleared: &[(i64, i64)],
    ) -> Result<(Vec<bool>, Vec<Alarm>), StoreError> {
        let mut conn = self.writer().await?;
        let outcome: Result<_, sqlx::Error> = async {
        let mut tx = sqlx::Connection::begin(&mut *conn).await?;
        for rows in events.chunks(100) {
            let sql = format!(
                "INSERT INTO events (lift, at, kind, body) VALUES {}",
                super::parameter_rows(rows.len(), 4)
            );
            let mut query = sqlx::query(&sql);
            for row in rows {
                query = query
                    .bind(&row.lift)
                    .bind(row.at)
                    .bind(&row.kind)
                    .bind(&row.body);
            }
            query.execute(&mut *tx).await?;
        }
        crate::insights::insert(&mut tx, statuses).await?;
        let mut new = Vec::with_capacity(raised.len());
        for alarm in raised {
            let place = alarm.node.unwrap_or(Place { id: None, net: 0 });
            let inserted = sqlx::query(
                "INSERT INTO alarms (id, lift, kind, net, node, code, severity, text, raised) VALUES ($1, $2, $3, $4, $5, $6, $7, $8, $9) \
                 ON CONFLICT (lift, kind, net, node, code) WHERE cleared IS NULL DO NOTHING",
            )
            .bind(alarm.id)
            .bind(&alarm.lift)
            .bind(alarm.kind.name())
            .bind(i64::from(place.net))
            .bind(i64::from(place.id.unwrap_or(0)))
            .bind(&alarm.code)
            .bind(alarm.severity.name())
            .bind(&alarm.text)
            .bind(nxg::msg::parse_time(&alarm.raised).unwrap_or(0))
            .execute(&mut *tx)
            .await?;
            new.push(inserted.rows_affected() == 1);
        }
        let mut done = Vec::with_capacity(cleared.len());
        for (id, at) in cleared {
            let row = sqlx::query(
                "UPDATE alarms SET cleared = $1 WHERE id = $2 AND cleared IS NULL RETURNING *",
            )
            .bind(at)
            .bind(id)
            .fetch_optional(&mut *tx)
            .await?;
            if let Some(row) = row {
                done.push(alarm_from(&row)?);
            }
        }
        tx.commit().await?;
        Ok((new, done))
        }
        .await;
        self.settle(conn, outcome).await
    }

    /// A lift's events, oldest first: from `since` (ms) on, or the newest `limit` without it.
    pub async fn event_log(
        &self,
        lift: &str,
        since: Option<i64>,
        limit: u32,
    ) -> Result<Vec<String>, StoreError> {
        let limit = i64::from(limit.clamp(1, 10_000));
        let rows = match since {
            Some(since) => {
                sqlx::query(
                    "SELECT body FROM events WHERE lift = $1 AND at >= $2 ORDER BY at LIMIT $3",
                )
                .bind(lift)
                .bind(since)
                .bind(limit)
                .fetch_all(&self.pool)
                .await?
            }
            None => {
                sqlx::query(
                    "SELECT body FROM (SELECT body, at FROM events WHERE lift = $1 ORDER BY at DESC LIMIT $2) newest ORDER BY at",
                )
                .bind(lift)
                .bind(limit)
                .fetch_all(&self.pool)
                .await?
            }
        };
        rows.iter()
            .map(|r| r.try_get("body"))
            .collect::<Result<_, _>>()
            .map_err(StoreError::from)
    }

    /// Delete events older than `before` (ms); how many went.
    pub async fn forget_events(&self, before: i64) -> Result<u64, StoreError> {
        let done = sqlx::query("DELETE FROM events WHERE at < $1")
            .bind(before)
            .execute(&self.pool)
            .await?;
        Ok(done.rows_affected())
    }

    /// Acknowledge alarm `id` of a lift of `domain`: `Ok(None)` if there is no such alarm,
    /// `Ok(Some(false))` if it was acknowledged already.
    pub async fn acknowledge_alarm(
        &self,
        domain: &str,
        id: i64,
        by: &str,
        comment: &str,
        at: i64,
    ) -> Result<Option<bool>, StoreError> {
        let done = sqlx::query(
            "UPDATE alarms SET ack_by = $1, ack_at = $2, ack_comment = $3 WHERE id = $4 AND ack_at IS NULL \
             AND lift IN (SELECT id FROM gateways WHERE domain = $5)",
        )
        .bind(by)
        .bind(at)
        .bind(comment)
        .bind(id)
        .bind(domain)
        .execute(&self.pool)
        .await?;
        if done.rows_affected() == 1 {
            return Ok(Some(true));
        }
        Ok(self.alarm_of(domain, id).await?.map(|_| false))
    }

    /// Alarm `id`.
    pub async fn alarm(&self, id: i64) -> Result<Option<Alarm>, StoreError> {
        let row = sqlx::query("SELECT * FROM alarms WHERE id = $1")
            .bind(id)
            .fetch_optional(&self.pool)
            .await?;
        Ok(row.as_ref().map(alarm_from).transpose()?)
    }

    /// Alarm `id` if it is of a lift of `domain`.
    pub async fn alarm_of(&self, domain: &str, id: i64) -> Result<Option<Alarm>, StoreError> {
        let row = sqlx::query(
            "SELECT a.* FROM alarms a JOIN gateways g ON g.id = a.lift WHERE a.id = $1 AND g.domain = $2",
        )
        .bind(id)
        .bind(domain)
        .fetch_optional(&self.pool)
        .await?;
        Ok(row.as_ref().map(alarm_from).transpose()?)
    }

    /// The alarms of `domain`'s lifts, newest first.
    pub async fn alarms(
        &self,
        domain: &str,
        filter: &AlarmFilter,
    ) -> Result<Vec<Alarm>, StoreError> {
        let mut sql = String::from(
            "SELECT a.* FROM alarms a JOIN gateways g ON g.id = a.lift WHERE g.domain = $1",
        );
        if filter.active {
            sql.push_str(" AND a.cleared IS NULL");
        }
        if filter.lift.is_some() {
            sql.push_str(" AND a.lift = $3");
        }
        sql.push_str(" ORDER BY a.raised DESC LIMIT $2");
        let mut query = sqlx::query(&sql)
            .bind(domain)
            .bind(i64::from(filter.limit.clamp(1, 10_000)));
        if let Some(lift) = &filter.lift {
            query = query.bind(lift);
        }
        let rows = query.fetch_all(&self.pool).await?;
        rows.iter()
            .map(alarm_from)
            .collect::<Result<_, _>>()
            .map_err(StoreError::from)
    }

    /// Every active alarm with its condition (to rebuild the index at start).
    pub async fn active_alarms(&self) -> Result<Vec<(Condition, i64)>, StoreError> {
        let rows = sqlx::query("SELECT * FROM alarms WHERE cleared IS NULL")
            .fetch_all(&self.pool)
            .await?;
        conditions(&rows)
    }

    /// The active alarms of `lifts`, by condition: in statements of a few lengths, however
    /// many lifts came online at once.
    pub async fn active_alarms_of(
        &self,
        lifts: &[String],
    ) -> Result<Vec<(Condition, i64)>, StoreError> {
        let mut active = Vec::new();
        for lifts in crate::chunks_by_binary_digits(lifts, 256) {
            let sql = format!(
                "SELECT * FROM alarms WHERE cleared IS NULL AND lift IN ({})",
                super::parameter_rows(lifts.len(), 1)
            );
            let mut query = sqlx::query(&sql);
            for lift in lifts {
                query = query.bind(lift);
            }
            active.extend(conditions(&query.fetch_all(&self.pool).await?)?);
        }
        Ok(active)
    }

    /// The most severe active alarm of each of `domain`'s lifts that has one.
    pub async fn worst_alarms(&self, domain: &str) -> Result<HashMap<String, Alarm>, StoreError> {
        let active = AlarmFilter {
            active: true,
            lift: None,
            limit: 10_000,
        };
        let mut worst: HashMap<String, Alarm> = HashMap::new();
        for alarm in self.alarms(domain, &active).await? {
            let keep = worst
                .get(&alarm.lift)
                .is_some_and(|w| w.severity >= alarm.severity);
            if !keep {
                worst.insert(alarm.lift.clone(), alarm);
            }
        }
        Ok(worst)
    }

    /// Queue a webhook notification.
    pub async fn enqueue_webhook(
        &self,
        url: &str,
        lift: &str,
        body: &str,
        at: i64,
    ) -> Result<(), StoreError> {
        sqlx::query(
            "INSERT INTO webhook_outbox (id, url, body, lift, created, attempts, next_at) VALUES ($1, $2, $3, $4, $5, 0, $5)",
        )
        .bind(new_id())
        .bind(url)
        .bind(body)
        .bind(lift)
        .bind(at)
        .execute(&self.pool)
        .await?;
        Ok(())
    }

    /// Notifications due for an attempt at `now` (ms), oldest first.
    pub async fn due_webhooks(&self, now: i64, limit: u32) -> Result<Vec<OutboxEntry>, StoreError> {
        let rows = sqlx::query(
            "SELECT * FROM webhook_outbox WHERE delivered IS NULL AND given_up IS NULL AND next_at <= $1 ORDER BY created LIMIT $2",
        )
        .bind(now)
        .bind(i64::from(limit))
        .fetch_all(&self.pool)
        .await?;
        rows.iter()
            .map(|r| {
                Ok(OutboxEntry {
                    id: r.try_get("id")?,
                    url: r.try_get("url")?,
                    body: r.try_get("body")?,
                    lift: r.try_get("lift")?,
                    attempts: u32::try_from(r.try_get::<i64, _>("attempts")?).unwrap_or(u32::MAX),
                    created: r.try_get("created")?,
                })
            })
            .collect::<Result<_, sqlx::Error>>()
            .map_err(StoreError::from)
    }

    /// When the next undelivered notification is due (ms), if any waits.
    pub async fn next_webhook_due(&self) -> Result<Option<i64>, StoreError> {
        let row = sqlx::query(
            "SELECT MIN(next_at) AS next FROM webhook_outbox WHERE delivered IS NULL AND given_up IS NULL",
        )
        .fetch_one(&self.pool)
        .await?;
        Ok(row.try_get("next")?)
    }

    /// Record an attempt: delivered at `at`, or to be tried again at `next_at` (or given up,
    /// `next_at` absent) after `error`.
    pub async fn webhook_attempt(
        &self,
        id: i64,
        at: i64,
        outcome: Result<(), (&str, Option<i64>)>,
    ) -> Result<(), StoreError> {
        let query = match outcome {
            Ok(()) => sqlx::query(
                "UPDATE webhook_outbox SET attempts = attempts + 1, delivered = $1, last_error = NULL WHERE id = $2",
            )
            .bind(at)
            .bind(id),
            Err((error, Some(next_at))) => sqlx::query(
                "UPDATE webhook_outbox SET attempts = attempts + 1, next_at = $1, last_error = $2 WHERE id = $3",
            )
            .bind(next_at)
            .bind(error.to_owned())
            .bind(id),
            Err((error, None)) => sqlx::query(
                "UPDATE webhook_outbox SET attempts = attempts + 1, given_up = $1, last_error = $2 WHERE id = $3",
            )
            .bind(at)
            .bind(error.to_owned())
            .bind(id),
        };
        query.execute(&self.pool).await?;
        Ok(())
    }

    /// Notifications not yet delivered (nor given up).
    pub async fn pending_webhooks(&self) -> Result<i64, StoreError> {
        let row = sqlx::query(
            "SELECT COUNT(*) AS n FROM webhook_outbox WHERE delivered IS NULL AND given_up IS NULL",
        )
        .fetch_one(&self.pool)
        .await?;
        Ok(row.try_get("n")?)
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// Run by the store's tests on SQLite and PostgreSQL: a condition has one active alarm,
    /// whichever process raises it (a second raise is no new alarm), and a new one once it
    /// cleared.
    pub(crate) async fn one_active_alarm_per_condition(store: &Store) {
        let condition = Condition {
            lift: "1050-4096-ALARM".into(),
            kind: Kind::LiftOffline,
            place: None,
            code: String::new(),
        };
        let raise = |id: i64| Alarm::raised(id, &condition, Severity::Major, "offline", 1000);
        let (new, _) = store
            .write_alarm_batch(&[], &[], &[raise(11), raise(12)], &[])
            .await
            .unwrap();
        assert_eq!(new, [true, false]);
        let (new, _) = store
            .write_alarm_batch(&[], &[], &[raise(13)], &[])
            .await
            .unwrap();
        assert_eq!(new, [false], "raised by another process before");
        assert_eq!(
            store
                .active_alarms_of(std::slice::from_ref(&condition.lift))
                .await
                .unwrap(),
            [(condition.clone(), 11)]
        );
        let (new, cleared) = store
            .write_alarm_batch(&[], &[], &[], &[(11, 2000)])
            .await
            .unwrap();
        assert!(new.is_empty());
        assert_eq!(cleared.len(), 1);
        let (new, _) = store
            .write_alarm_batch(&[], &[], &[raise(14)], &[])
            .await
            .unwrap();
        assert_eq!(new, [true]);
        assert_eq!(
            store
                .active_alarms_of(std::slice::from_ref(&condition.lift))
                .await
                .unwrap(),
            [(condition.clone(), 14)]
        );
        // Many lifts at once (a reconnect storm's): each active alarm of those asked for,
        // whatever the statement lengths they are asked in, and none of others.
        let others: Vec<Alarm> = (0..300)
            .map(|n| {
                let lift = format!("1050-4096-STORM{n}");
                let condition = Condition {
                    lift,
                    ..condition.clone()
                };
                Alarm::raised(100 + n, &condition, Severity::Major, "offline", 1000)
            })
            .collect();
        store
            .write_alarm_batch(&[], &[], &others, &[])
            .await
            .unwrap();
        let asked: Vec<String> = (0..300)
            .filter(|n| n % 3 != 0)
            .map(|n| format!("1050-4096-STORM{n}"))
            .chain([condition.lift.clone(), "1050-4096-NONE".into()])
            .collect();
        let mut ids: Vec<i64> = store
            .active_alarms_of(&asked)
            .await
            .unwrap()
            .into_iter()
            .map(|(_, id)| id)
            .collect();
        ids.sort_unstable();
        let expected: Vec<i64> = std::iter::once(14)
            .chain((0..300).filter(|n| n % 3 != 0).map(|n| 100 + n))
            .collect();
        assert_eq!(ids, expected);
    }
}
