//! An object's history over any period as at most N buckets spanning all of it
//! (docs/PORTAL.md §History): from the raw values for a short period, from the roll-ups for a
//! long one, raw values at the edges where a roll-up would reach beyond the period and for the
//! last minutes not rolled up yet.

use crate::rollups::{Bucket, Grain};
use crate::{Store, StoreError};

/// Periods up to this long are read from the raw values (ms): 6 h.
const RAW_SPAN: i64 = 6 * 3_600_000;

/// Raw values read for one answer at most; a period that holds more is read from the roll-ups.
const RAW_LIMIT: usize = 200_000;

/// Periods longer than this are read from the hour roll-ups (ms): 90 days.
const MINUTE_SPAN: i64 = 90 * 86_400_000;

/// Where an answer's buckets were made from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    /// Every value of the period.
    Raw,
    /// The minute roll-ups (raw values at the edges).
    Minute,
    /// The hour roll-ups (minute roll-ups and raw values at the edges).
    Hour,
}

impl Source {
    /// The name in the API.
    pub fn name(self) -> &'static str {
        match self {
            Source::Raw => "raw",
            Source::Minute => "minute",
            Source::Hour => "hour",
        }
    }
}

/// An object's values from `from` to `to` in at most `points` buckets of equal length, the
/// empty ones left out; each bucket's `at` is its start.
#[derive(Debug, Clone, PartialEq)]
pub struct Buckets {
    /// What they were made from.
    pub source: Source,
    /// The length of a bucket (ms).
    pub width: i64,
    /// The buckets holding values, oldest first.
    pub buckets: Vec<Bucket>,
}

impl Store {
    /// The values of one object of `lift` from `from` to `to` (ms, both included) in at most
    /// `points` buckets spanning the period.
    pub async fn history(
        &self,
        lift: &str,
        mplex: &str,
        from: i64,
        to: i64,
        points: usize,
    ) -> Result<Buckets, StoreError> {
        let to = to.max(from);
        let points = points.max(1);
        // In i128: a period may span all of i64.
        let span = i128::from(to) - i128::from(from);
        let width =
            (span + 1).div_euclid(points as i128) + i128::from((span + 1) % points as i128 != 0);
        let width = i64::try_from(width.max(1)).unwrap_or(i64::MAX);
        let mut out = Folded::new(from, width);
        if span <= i128::from(RAW_SPAN) {
            let rows = self.values(lift, mplex, from, to, RAW_LIMIT + 1).await?;
            if rows.len() <= RAW_LIMIT {
                out.raw(&rows);
                return Ok(out.done(Source::Raw));
            }
        }
        // Rolled up to `done`: what lies beyond is read raw (a few minutes at most).
        let done = self.rolled_up_to().await?.unwrap_or(i64::MIN);
        let source = if span > i128::from(MINUTE_SPAN) {
            Source::Hour
        } else {
            Source::Minute
        };
        let end = to.saturating_add(1).min(done);
        if source == Source::Hour {
            let hours = (Grain::Hour.ceil(from), Grain::Hour.floor(end));
            if hours.0 < hours.1 {
                out.rolled(
                    &self
                        .roll_ups(Grain::Hour, lift, mplex, hours.0, hours.1)
                        .await?,
                );
                self.minutes_and_raw(&mut out, lift, mplex, from, hours.0, done)
                    .await?;
                self.minutes_and_raw(&mut out, lift, mplex, hours.1, to + 1, done)
                    .await?;
                return Ok(out.done(source));
            }
        }
        self.minutes_and_raw(&mut out, lift, mplex, from, to.saturating_add(1), done)
            .await?;
        Ok(out.done(source))
    }

    /// Fold `[from, until)` into `out`: the whole minutes rolled up by `done` from their
    /// roll-ups, the rest raw.
    async fn minutes_and_raw(
        &self,
        out: &mut Folded,
        lift: &str,
        mplex: &str,
        from: i64,
        until: i64,
        done: i64,
    ) -> Result<(), StoreError> {
        if from >= until {
            return Ok(());
        }
        let minutes = (
            Grain::Minute.ceil(from),
            Grain::Minute.floor(until.min(done)),
        );
        if minutes.0 >= minutes.1 {
            let rows = self.values(lift, mplex, from, until - 1, RAW_LIMIT).await?;
            out.raw(&rows);
            return Ok(());
        }
        out.rolled(
            &self
                .roll_ups(Grain::Minute, lift, mplex, minutes.0, minutes.1)
                .await?,
        );
        for (a, b) in [(from, minutes.0), (minutes.1, until)] {
            if a < b {
                let rows = self.values(lift, mplex, a, b - 1, RAW_LIMIT).await?;
                out.raw(&rows);
            }
        }
        Ok(())
    }
}

/// Buckets of `width` from `from`, gathered from raw values and roll-ups in any order.
struct Folded {
    from: i64,
    width: i64,
    buckets: std::collections::BTreeMap<i64, Bucket>,
}

impl Folded {
    fn new(from: i64, width: i64) -> Folded {
        Folded {
            from,
            width,
            buckets: std::collections::BTreeMap::new(),
        }
    }

    fn add(&mut self, bucket: Bucket) {
        let index =
            (i128::from(bucket.at) - i128::from(self.from)).div_euclid(i128::from(self.width));
        let start = i64::try_from(i128::from(self.from) + index * i128::from(self.width))
            .unwrap_or(bucket.at);
        let index = i64::try_from(index).unwrap_or(i64::MAX);
        match self.buckets.entry(index) {
            std::collections::btree_map::Entry::Occupied(mut e) => e.get_mut().merge(&bucket),
            std::collections::btree_map::Entry::Vacant(e) => {
                e.insert(Bucket {
                    at: start,
                    ..bucket
                });
            }
        }
    }

    fn raw(&mut self, rows: &[(i64, String)]) {
        for (at, value) in rows {
            self.add(Bucket::of(*at, *at, value));
        }
    }

    fn rolled(&mut self, rows: &[Bucket]) {
        for row in rows {
            self.add(row.clone());
        }
    }

    fn done(self, source: Source) -> Buckets {
        Buckets {
            source,
            width: self.width,
            buckets: self.buckets.into_values().collect(),
        }
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::TelemetryRow;

    fn row(at: i64, value: &str) -> TelemetryRow {
        TelemetryRow {
            lift: "1050-4096-HIST".into(),
            mplex: "0x638301".into(),
            node: 0,
            value: value.into(),
            at,
        }
    }

    /// Run by the store's tests on SQLite and PostgreSQL: a week of values every 10 s with a
    /// spike at each end and one in the middle, rolled up; the answers for the week, a day and
    /// an hour span their period, keep the spikes in their min/max, count every value once.
    pub(crate) async fn a_week_in_a_thousand_buckets(store: &Store) {
        let start = 1_700_000_000_000i64 - 1_700_000_000_000i64 % 3_600_000 + 17_000;
        let step = 10_000;
        let n = 7 * 8640;
        let value = |i: i64| match i {
            0 => "-500".to_owned(),
            i if i == n / 2 => "9000".to_owned(),
            i if i == n - 1 => "7777".to_owned(),
            i => (i % 100).to_string(),
        };
        let rows: Vec<TelemetryRow> = (0..n).map(|i| row(start + i * step, &value(i))).collect();
        for chunk in rows.chunks(10_000) {
            store.telemetry(chunk).await.unwrap();
        }
        let last = start + (n - 1) * step;
        // Rolled up to an hour after the last value, in rounds of at most an hour.
        let now = last + 3_600_000;
        let mut rounds = 0;
        while store.rolled_up_to().await.unwrap()
            < Some(Grain::Minute.floor(now - crate::rollups::LAG_MS))
        {
            store.roll_up(now).await.unwrap();
            rounds += 1;
            assert!(rounds < 400, "the roll-up makes progress");
        }
        let (lift, mplex) = ("1050-4096-HIST", "0x638301");
        let week = store.history(lift, mplex, start, last, 1000).await.unwrap();
        assert_eq!(week.source, Source::Minute);
        assert!(
            week.buckets.len() <= 1000 && week.buckets.len() > 990,
            "{}",
            week.buckets.len()
        );
        assert_eq!(week.buckets.first().unwrap().at, start);
        assert_eq!(week.buckets.last().unwrap().last, "7777");
        assert_eq!(week.buckets.iter().map(|b| b.count).sum::<i64>(), n);
        let lows: Vec<f64> = week.buckets.iter().filter_map(|b| b.min).collect();
        let highs: Vec<f64> = week.buckets.iter().filter_map(|b| b.max).collect();
        assert_eq!(lows.iter().copied().fold(f64::INFINITY, f64::min), -500.0);
        assert!(highs.contains(&9000.0) && highs.contains(&7777.0));
        // A period that starts and ends mid-minute counts exactly its values.
        let from = start + 25 * 3_600_000 + 35_000;
        let to = from + 24 * 3_600_000 + 10_000;
        let day = store.history(lift, mplex, from, to, 1000).await.unwrap();
        let expected = rows.iter().filter(|r| r.at >= from && r.at <= to).count() as i64;
        assert_eq!(day.buckets.iter().map(|b| b.count).sum::<i64>(), expected);
        assert!(day.buckets.first().unwrap().at >= from);
        // An hour is read raw.
        let hour = store
            .history(lift, mplex, start, start + 3_599_999, 1000)
            .await
            .unwrap();
        assert_eq!(hour.source, Source::Raw);
        assert_eq!(hour.buckets.iter().map(|b| b.count).sum::<i64>(), 360);
        assert_eq!(hour.buckets[0].min, Some(-500.0));
        // A value stored late, in a minute rolled up long ago: rolled up again, not added twice.
        store.telemetry(&[row(start + 5, "-900")]).await.unwrap();
        store.rewind_roll_ups(start + 5);
        store.roll_up(now).await.unwrap();
        let week = store.history(lift, mplex, start, last, 1000).await.unwrap();
        assert_eq!(week.buckets.iter().map(|b| b.count).sum::<i64>(), n + 1);
        assert_eq!(week.buckets[0].min, Some(-900.0));
        let hours = store
            .roll_ups(Grain::Hour, lift, mplex, start - 17_000, last + 1)
            .await
            .unwrap();
        assert_eq!(hours.iter().map(|b| b.count).sum::<i64>(), n + 1);
        assert_eq!(hours[0].min, Some(-900.0));
        assert!(store.forget_roll_ups(now + 3_600_000).await.unwrap() > 0);
    }
}
