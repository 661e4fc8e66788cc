//! Lift insights (docs/PORTAL.md §Availability, §Monthly report, §Trends): availability and
//! fault figures of any period from what the portal stored, an account's monthly report, and
//! trend rules that see wear before it fails. The figures are computed sans-IO
//! ([`availability`], [`trends`]); this module gathers what they read.

pub mod availability;
pub mod trends;

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, PoisonError};

use cloud_store::{Lifts, Store, StoreError, Timeline};
use cloud_types::insights::{LiftFigures, MonthAvailability, MonthlyReport};
use cloud_types::lifts::shown_id;
use cloud_types::users::Account;

use crate::config::Insights;
use availability::Counters;

/// The figures of `lifts` from `from` to `to` (ms, `to` excluded), in the order of their ids.
pub async fn figures(
    store: &Store,
    insights: &Insights,
    lifts: Lifts<'_>,
    from: i64,
    to: i64,
) -> Result<Vec<LiftFigures>, StoreError> {
    let with = figures_and_timelines(store, insights, lifts, from, to).await?;
    Ok(with.into_iter().map(|(figures, _)| figures).collect())
}

/// [`figures`], each with the lift's statuses it was made from (the lift page draws them).
pub async fn figures_and_timelines(
    store: &Store,
    insights: &Insights,
    lifts: Lifts<'_>,
    from: i64,
    to: i64,
) -> Result<Vec<(LiftFigures, Timeline)>, StoreError> {
    // One row per lift: the timelines name the lifts too.
    let mut timelines: Vec<(String, Timeline)> = store
        .timelines(lifts, from, to)
        .await?
        .into_iter()
        .collect();
    timelines.sort_by(|a, b| a.0.cmp(&b.0));
    let mut faults = store.faults(lifts, from, to).await?;
    let objects =
        [insights.trips, insights.door_cycles, insights.reopenings].map(|m| m.to_string());
    let mplexes = objects.each_ref().map(String::as_str);
    let mut counters = store.counters_at(lifts, &mplexes, from, to).await?;
    Ok(timelines
        .into_iter()
        .map(|(id, timeline)| {
            let edges = counters.remove(&id).unwrap_or_default();
            let edge = |i: usize| edges.get(i).copied().unwrap_or_default();
            let counters = Counters {
                trips: edge(0),
                door_cycles: edge(1),
                reopenings: edge(2),
            };
            let figures = availability::figures(
                shown_id(&id),
                from,
                to,
                &timeline,
                faults.remove(&id).unwrap_or_default(),
                counters,
            );
            (figures, timeline)
        })
        .collect())
}

/// Each lift's availability from `from` to `to` (ms) from its statuses alone, by registry key:
/// what the fleet's column and a report's past months need, for a fraction of the figures'
/// cost.
pub async fn availabilities(
    store: &Store,
    lifts: Lifts<'_>,
    from: i64,
    to: i64,
) -> Result<Availabilities, StoreError> {
    Ok(store
        .timelines(lifts, from, to)
        .await?
        .into_iter()
        .map(|(lift, timeline)| {
            let availability = availability::integrate(&timeline, from, to).availability();
            (lift, availability)
        })
        .collect())
}

/// The availability of each lift of an account over the last [`Recent::DAYS`] days, as the fleet
/// page shows it: computed at most once per [`Recent::FRESH`] and account (every open fleet
/// page refreshes itself every ten seconds).
#[derive(Default)]
pub struct Recent {
    by_domain: std::sync::Mutex<HashMap<String, (std::time::Instant, Arc<Availabilities>)>>,
}

/// Each lift's availability by registry key (none where nothing was seen).
pub type Availabilities = HashMap<String, Option<f64>>;

impl Recent {
    /// The days the figure covers.
    pub const DAYS: i64 = 30;
    /// How long a figure is shown before it is computed again.
    pub const FRESH: std::time::Duration = std::time::Duration::from_secs(60);

    /// The lifts of `domain` by registry key.
    pub async fn of(&self, store: &Store, domain: &str) -> Result<Arc<Availabilities>, StoreError> {
        let fresh = |by: &HashMap<_, (std::time::Instant, Arc<_>)>| {
            by.get(domain)
                .filter(|(at, _)| at.elapsed() < Self::FRESH)
                .map(|(_, figures)| Arc::clone(figures))
        };
        if let Some(figures) = fresh(
            &self
                .by_domain
                .lock()
                .unwrap_or_else(PoisonError::into_inner),
        ) {
            return Ok(figures);
        }
        let to = cloud_types::now_ms();
        let lifts = Lifts { domain, lift: None };
        let figures =
            Arc::new(availabilities(store, lifts, to - Self::DAYS * 86_400_000, to).await?);
        self.by_domain
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .insert(
                domain.to_owned(),
                (std::time::Instant::now(), Arc::clone(&figures)),
            );
        Ok(figures)
    }
}

/// The availability of an account's lifts together over a month: their time in service over
/// in and out of service.
async fn month_availability(
    store: &Store,
    lifts: Lifts<'_>,
    month: Month,
) -> Result<MonthAvailability, StoreError> {
    let timelines = store.timelines(lifts, month.start(), month.end()).await?;
    let mut all = availability::Integrated::default();
    for timeline in timelines.values() {
        let time = availability::integrate(timeline, month.start(), month.end());
        for (sum, ms) in all.ms.iter_mut().zip(time.ms) {
            *sum += ms;
        }
    }
    Ok(MonthAvailability {
        month: month.to_string(),
        availability: all.availability(),
    })
}

/// A month (UTC) as `YYYY-MM` and its first and last millisecond + 1.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Month {
    year: i32,
    month: time::Month,
}

impl Month {
    /// `YYYY-MM`, years 1970–9999.
    pub fn parse(text: &str) -> Option<Month> {
        let (y, m) = text.split_once('-')?;
        if y.len() != 4 || m.len() != 2 {
            return None;
        }
        let year: i32 = y.parse().ok().filter(|y| (1970..=9999).contains(y))?;
        let month = time::Month::try_from(m.parse::<u8>().ok()?).ok()?;
        Some(Month { year, month })
    }

    /// The month a request asks for: `YYYY-MM`, or without one the last complete month; none
    /// for a text that is no month.
    pub fn asked(text: Option<&str>) -> Option<Month> {
        match text {
            Some(text) => Month::parse(text),
            None => Some(Month::of(cloud_types::now_ms()).previous()),
        }
    }

    /// The month `at` (ms) is in.
    pub fn of(at: i64) -> Month {
        let date = time::OffsetDateTime::from_unix_timestamp(at.div_euclid(1000))
            .unwrap_or(time::OffsetDateTime::UNIX_EPOCH);
        Month {
            year: date.year(),
            month: date.month(),
        }
    }

    /// The month before.
    pub fn previous(self) -> Month {
        match self.month {
            time::Month::January => Month {
                year: self.year - 1,
                month: time::Month::December,
            },
            m => Month {
                year: self.year,
                month: m.previous(),
            },
        }
    }

    /// The month after.
    pub fn next(self) -> Month {
        match self.month {
            time::Month::December => Month {
                year: self.year + 1,
                month: time::Month::January,
            },
            m => Month {
                year: self.year,
                month: m.next(),
            },
        }
    }

    /// Its first millisecond.
    pub fn start(self) -> i64 {
        time::Date::from_calendar_date(self.year, self.month, 1)
            .map_or(0, |d| d.midnight().assume_utc().unix_timestamp() * 1000)
    }

    /// The first millisecond of the month after.
    pub fn end(self) -> i64 {
        self.next().start()
    }
}

impl std::fmt::Display for Month {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:04}-{:02}", self.year, u8::from(self.month))
    }
}

/// `account`'s report of `month`: its lifts, the least available first, against its target,
/// with the three months before.
pub async fn monthly(
    store: &Store,
    insights: &Insights,
    account: &Account,
    month: Month,
) -> Result<MonthlyReport, StoreError> {
    let lifts = Lifts {
        domain: &account.domain,
        lift: None,
    };
    let before = [3, 2, 1].map(|back| (0..back).fold(month, |m, _| m.previous()));
    // The past months need only their statuses; all four are asked at once.
    let (figures, m1, m2, m3) = tokio::try_join!(
        figures(store, insights, lifts, month.start(), month.end()),
        month_availability(store, lifts, before[0]),
        month_availability(store, lifts, before[1]),
        month_availability(store, lifts, before[2]),
    )?;
    let mut figures = figures;
    let months = vec![m1, m2, m3];
    let mut faults_by_kind = BTreeMap::new();
    for lift in &figures {
        for (code, n) in &lift.faults_by_kind {
            *faults_by_kind.entry(code.clone()).or_insert(0) += n;
        }
    }
    figures.sort_by(|a, b| match (a.availability, b.availability) {
        (Some(a), Some(b)) => a.total_cmp(&b),
        (Some(_), None) => std::cmp::Ordering::Less,
        (None, Some(_)) => std::cmp::Ordering::Greater,
        (None, None) => std::cmp::Ordering::Equal,
    });
    Ok(MonthlyReport {
        month: month.to_string(),
        account: account.name.clone(),
        target: store
            .availability_target(&account.name)
            .await?
            .unwrap_or(insights.target),
        availability: availability::combined(&figures),
        faults_by_kind,
        trend: months,
        lifts: figures,
    })
}

/// The figures as CSV (RFC 4180, a header row of
/// [`cloud_types::insights::CSV_COLUMNS`]); empty fields for figures that are none.
pub fn csv(lifts: &[LiftFigures]) -> String {
    use std::fmt::Write;
    let mut out = cloud_types::insights::CSV_COLUMNS.join(",");
    out.push_str("\r\n");
    let opt = |v: Option<f64>| v.map(|v| v.to_string()).unwrap_or_default();
    let count = |v: Option<u64>| v.map(|v| v.to_string()).unwrap_or_default();
    for l in lifts {
        let kinds: Vec<String> = l
            .faults_by_kind
            .iter()
            .map(|(k, n)| format!("{k}={n}"))
            .collect();
        let _ = write!(
            out,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{}\r\n",
            crate::csv::cell(&l.lift),
            opt(l.availability),
            l.in_service_s,
            l.out_of_service_s,
            l.offline_s,
            l.unknown_s,
            l.faults,
            crate::csv::cell(&kinds.join(";")),
            count(l.trips),
            opt(l.faults_per_1000_trips),
            opt(l.mtbf_s),
            opt(l.mttr_s),
            count(l.door_cycles),
            count(l.reopenings),
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn months_cut_at_midnight_utc_and_wrap_at_the_year() {
        let m = Month::parse("2026-01").unwrap();
        assert_eq!(m.start(), 1_767_225_600_000);
        assert_eq!(m.previous().to_string(), "2025-12");
        assert_eq!(m.end(), Month::parse("2026-02").unwrap().start());
        assert_eq!(Month::of(m.end() - 1), m);
        for bad in ["2026-13", "2026-1", "26-01", "1969-12", "2026-00", "x"] {
            assert_eq!(Month::parse(bad), None, "{bad}");
        }
    }

    #[test]
    fn csv_quotes_what_would_break_it_or_run_as_a_formula() {
        let mut l = LiftFigures {
            lift: "=1+1,x".into(),
            ..LiftFigures::default()
        };
        l.faults_by_kind.insert("0xFF01".into(), 2);
        l.faults_by_kind.insert("0xF001".into(), 1);
        let text = csv(&[l]);
        let row = text.lines().nth(1).unwrap();
        assert!(
            row.starts_with("\"'=1+1,x\",,0,0,0,0,0,0xF001=1;0xFF01=2,"),
            "{row}"
        );
        assert_eq!(text.lines().next().unwrap().split(',').count(), 14);
    }
}
