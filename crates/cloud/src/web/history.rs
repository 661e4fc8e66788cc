//! The history page: the stored values of one or several objects over a period, one SVG chart
//! each on the same time axis, drawn by the portal from at most a thousand buckets spanning the
//! whole period (docs/PORTAL.md §History) — numbers as a step chart of each bucket's last value
//! over a band from its smallest to its largest, with their unit; choices (lift state, door
//! state…) as a state timeline — with hover values, drag to zoom, live update while the period
//! ends now, and the CSV of what is shown (every value, or the buckets of a long period).

use std::sync::Arc;

use axum::extract::{Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use maud::{html, Markup};
use nxg::mplex::Mplex;
use serde::Deserialize;

use super::i18n::Locale;
use super::lift::{describe, Described};
use super::page::{layout, lift_path, problem, time, unavailable, utc};
use super::{owned, SignedIn};
use crate::state::AppState;
use cloud_store::Bucket;

/// Objects on one page at most.
const MAX_SERIES: usize = 6;

/// Buckets a chart is drawn from: about one per pixel of its width.
const POINTS: usize = 1000;

/// Values a CSV lists one by one at most; a period holding more is exported as its buckets.
const CSV_RAW: usize = 100_000;

#[derive(Deserialize)]
pub(super) struct HistoryQuery {
    /// One object, or several separated by commas (address forms or names).
    mplex: String,
    /// The period shown, ending now.
    minutes: Option<u32>,
    /// A fixed period instead (ms since the epoch), as a zoom leaves it.
    from: Option<i64>,
    to: Option<i64>,
}

/// The period a page shows: the last `minutes`, or a fixed one.
struct Period {
    from: i64,
    to: i64,
    /// `None`: a fixed period (no live update).
    minutes: Option<u32>,
}

impl Period {
    fn of(q: &HistoryQuery) -> Period {
        let now = cloud_types::now_ms();
        // Times the page cannot show are no period of its own (a hostile link is the last hour).
        let shown = |t: Option<i64>| t.filter(|t| (0..=cloud_types::LATEST_MS).contains(t));
        match (shown(q.from), shown(q.to)) {
            (Some(from), Some(to)) if from < to => Period {
                from,
                to: to.min(now.max(from + 1)),
                minutes: None,
            },
            _ => {
                let minutes = q.minutes.unwrap_or(60).clamp(1, 31 * 24 * 60);
                Period {
                    from: now - i64::from(minutes) * 60_000,
                    to: now,
                    minutes: Some(minutes),
                }
            }
        }
    }

    /// The query string of this period for `mplexes`.
    fn query(&self, mplexes: &str) -> String {
        let mut q = vec![("mplex", mplexes.to_owned())];
        match self.minutes {
            Some(m) => q.push(("minutes", m.to_string())),
            None => {
                q.push(("from", self.from.to_string()));
                q.push(("to", self.to.to_string()));
            }
        }
        serde_urlencoded::to_string(q).unwrap_or_default()
    }
}

/// One object's stored values over the period, in buckets.
struct Series {
    mplex: String,
    history: cloud_store::Buckets,
}

/// The objects of `q` on lift `id` with their values in its period, or the page that says why
/// not; the lift's key in the registry.
async fn shown(
    app: &AppState,
    who: &SignedIn,
    id: &str,
    q: &HistoryQuery,
) -> Result<(Vec<Mplex>, Vec<Series>, Period, String), Response> {
    let l = who.locale;
    let key = owned(app, who, id).await?.id;
    let mut mplexes = Vec::new();
    for text in q.mplex.split(',').map(str::trim).filter(|t| !t.is_empty()) {
        match app.names.resolve(text) {
            Ok(m) if !mplexes.contains(&m) => mplexes.push(m),
            Ok(_) => {}
            Err(e) => {
                let message = l.fill("mplex: {}", &[&e]);
                return Err(problem(StatusCode::BAD_REQUEST, who.viewer(), &message));
            }
        }
    }
    mplexes.truncate(MAX_SERIES);
    if mplexes.is_empty() {
        let message = l.fill("mplex: {}", &[&"—"]);
        return Err(problem(StatusCode::BAD_REQUEST, who.viewer(), &message));
    }
    let period = Period::of(q);
    // Each series its own statement (they may be long), all asked at once.
    let key = &key;
    let series = futures_util::future::try_join_all(mplexes.iter().map(|m| async move {
        let mplex = m.to_string();
        let history = app
            .store
            .history(key, &mplex, period.from, period.to, POINTS)
            .await?;
        Ok::<_, cloud_store::StoreError>(Series { mplex, history })
    }))
    .await
    .map_err(|e| unavailable(e, who.viewer()))?;
    Ok((mplexes, series, period, key.clone()))
}

/// `GET /lifts/{id}/history.csv?mplex=&minutes=` (or `from`/`to`): what the page shows, as CSV
/// (RFC 4180) with UTC times (ISO 8601): every value (`time,object,value`) when the period holds
/// at most [`CSV_RAW`] of each object, otherwise the buckets the charts are drawn from
/// (`time,object,min,max,last,count`, a bucket's time its start), which the first line says.
pub(super) async fn history_csv(
    State(app): State<Arc<AppState>>,
    who: SignedIn,
    Path(id): Path<String>,
    Query(q): Query<HistoryQuery>,
) -> Response {
    let (_, series, period, key) = match shown(&app, &who, &id, &q).await {
        Ok(s) => s,
        Err(r) => return r,
    };
    let mut raw = Vec::with_capacity(series.len());
    for s in &series {
        match app
            .store
            .values(&key, &s.mplex, period.from, period.to, CSV_RAW + 1)
            .await
        {
            Ok(rows) if rows.len() <= CSV_RAW => raw.push(rows),
            Ok(_) => break,
            Err(e) => return unavailable(e, who.viewer()),
        }
    }
    let mut csv = String::new();
    if raw.len() == series.len() {
        csv.push_str("time,object,value\r\n");
        for (s, rows) in series.iter().zip(&raw) {
            for (at, value) in rows {
                csv.push_str(&format!(
                    "{},{},{}\r\n",
                    iso(*at),
                    s.mplex,
                    crate::csv::cell(value)
                ));
            }
        }
    } else {
        let width = series.first().map_or(0, |s| s.history.width);
        csv.push_str(&format!(
            "# more than {CSV_RAW} values: one line per {} s bucket (its start, its smallest and largest number, its last value, how many)\r\n",
            width as f64 / 1000.0
        ));
        csv.push_str("time,object,min,max,last,count\r\n");
        for s in &series {
            for b in &s.history.buckets {
                let number = |v: Option<f64>| v.map_or_else(String::new, |v| v.to_string());
                csv.push_str(&format!(
                    "{},{},{},{},{},{}\r\n",
                    iso(b.at),
                    s.mplex,
                    number(b.min),
                    number(b.max),
                    crate::csv::cell(&b.last),
                    b.count
                ));
            }
        }
    }
    let names: Vec<&str> = series.iter().map(|s| s.mplex.as_str()).collect();
    let file = format!("{id}-{}.csv", names.join("-"));
    (
        [
            (header::CONTENT_TYPE, "text/csv; charset=utf-8".to_owned()),
            (header::CONTENT_DISPOSITION, attachment(&file)),
        ],
        csv,
    )
        .into_response()
}

/// `Content-Disposition` of a download named `file` (RFC 6266): the name with every
/// character but letters, digits, `.`, `-` and `_` replaced by `_` — a serial number is the
/// gateway's text, and no quote or `;` of it may end the parameter — once as plain ASCII and
/// once percent-encoded (`filename*`, RFC 8187) for browsers that prefer it.
fn attachment(file: &str) -> String {
    let safe: String = file
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_') {
                c
            } else {
                '_'
            }
        })
        .collect();
    format!("attachment; filename=\"{safe}\"; filename*=UTF-8''{safe}")
}

/// Milliseconds since the epoch as ISO 8601 UTC with milliseconds.
fn iso(ms: i64) -> String {
    let date = utc(ms.div_euclid(1000) * 1000);
    let (day, time) = date
        .trim_end_matches(" UTC")
        .split_once(' ')
        .unwrap_or((&date, ""));
    format!("{day}T{time}.{:03}Z", ms.rem_euclid(1000))
}

/// Chart geometry (SVG user units).
const W: f64 = 800.0;
const LEFT: f64 = 70.0;
const RIGHT: f64 = W - 10.0;

/// Where time `t` of `period` lies on the x axis.
fn x_of(t: i64, period: &Period) -> f64 {
    LEFT + (t - period.from) as f64 / (period.to - period.from).max(1) as f64 * (RIGHT - LEFT)
}

/// The frame every chart shares: the time axis with local times, the hover cursor and label,
/// and the data the script's hover and zoom read (`labels`: the names of a choice's values).
fn frame(
    period: &Period,
    height: f64,
    points: &[(i64, f64)],
    labels: Option<(i64, &[String])>,
    l: Locale,
    content: Markup,
) -> Markup {
    let bottom = height - 30.0;
    let data: Vec<String> = points.iter().map(|(t, v)| format!("{t}:{v}")).collect();
    let names = labels.map(|(min, list)| (min, serde_json::to_string(list).unwrap_or_default()));
    html! {
        svg.chart viewBox={ "0 0 " (W) " " (height) } role="img" aria-label=(l.t("history chart"))
            data-from=(period.from) data-to=(period.to) data-left=(LEFT) data-right=(RIGHT)
            data-points=(data.join(",")) data-min=[names.as_ref().map(|n| n.0)]
            data-labels=[names.as_ref().map(|n| n.1.as_str())] {
            line x1=(LEFT) y1="10" x2=(LEFT) y2=(bottom) class="axis" {}
            line x1=(LEFT) y1=(bottom) x2=(RIGHT) y2=(bottom) class="axis" {}
            (content)
            text x=(LEFT) y=(height - 8.0) class="label" data-ms=(period.from) { (utc(period.from)) }
            text x=(RIGHT) y=(height - 8.0) class="label" text-anchor="end" data-ms=(period.to) { (utc(period.to)) }
            line.cursor x1="0" y1="10" x2="0" y2=(bottom) visibility="hidden" {}
            rect.zoom x="0" y="10" width="0" height=(bottom - 10.0) visibility="hidden" {}
            text.hover x=(LEFT + 6.0) y="24" {}
        }
    }
}

/// A step chart of each bucket's last value over a band from its smallest to its largest
/// (drawn where a bucket held more than one value), the y axis labelled with `unit`.
fn line_chart(buckets: &[Bucket], width: i64, period: &Period, unit: &str, l: Locale) -> Markup {
    const H: f64 = 240.0;
    let bottom = H - 30.0;
    let points = last_numbers(buckets);
    let lo = buckets
        .iter()
        .filter_map(|b| b.min)
        .fold(f64::INFINITY, f64::min);
    let hi = buckets
        .iter()
        .filter_map(|b| b.max)
        .fold(f64::NEG_INFINITY, f64::max);
    let (lo, hi) = if (hi - lo).abs() < f64::EPSILON {
        (lo - 1.0, hi + 1.0)
    } else {
        (lo, hi)
    };
    let y = |v: f64| 10.0 + (hi - v) / (hi - lo) * (bottom - 10.0);
    let mut path = Vec::with_capacity(points.len() * 2 + 1);
    let mut previous: Option<f64> = None;
    for &(t, v) in &points {
        if let Some(p) = previous {
            path.push(format!("{:.1},{:.1}", x_of(t, period), y(p)));
        }
        path.push(format!("{:.1},{:.1}", x_of(t, period), y(v)));
        previous = Some(v);
    }
    if let Some(p) = previous {
        path.push(format!("{:.1},{:.1}", RIGHT, y(p)));
    }
    // The band: each bucket's smallest to largest, over the bucket's width.
    let bands: Vec<(f64, f64, f64, f64)> = buckets
        .iter()
        .filter(|b| b.count > 1)
        .filter_map(|b| {
            let (min, max) = (b.min?, b.max?);
            let x0 = x_of(b.at, period);
            let x1 = x_of((b.at + width).min(period.to), period);
            Some((x0, (x1 - x0).max(0.5), y(max), (y(min) - y(max)).max(0.5)))
        })
        .collect();
    let content = html! {
        text x=(LEFT - 6.0) y="16" class="label" text-anchor="end" { (hi) " " (unit) }
        text x=(LEFT - 6.0) y=(bottom) class="label" text-anchor="end" { (lo) " " (unit) }
        @for (x, w, top, h) in &bands {
            rect.band x=(format!("{x:.1}")) y=(format!("{top:.1}")) width=(format!("{w:.1}")) height=(format!("{h:.1}")) {}
        }
        polyline class="line" points=(path.join(" ")) {}
    };
    frame(period, H, &points, None, l, content)
}

/// Each bucket's last value that is a number, at the time it came.
fn last_numbers(buckets: &[Bucket]) -> Vec<(i64, f64)> {
    buckets
        .iter()
        .filter_map(|b| b.last.trim().parse::<f64>().ok().map(|v| (b.last_at, v)))
        .collect()
}

/// A state timeline: one band per stretch of time in one state, named where there is room.
fn state_chart(
    points: &[(i64, f64)],
    period: &Period,
    (min, names): (i64, &[String]),
    l: Locale,
) -> Markup {
    const H: f64 = 110.0;
    let name = |v: f64| {
        usize::try_from(v as i64 - min)
            .ok()
            .and_then(|i| names.get(i))
            .map_or_else(|| v.to_string(), Clone::clone)
    };
    let bands: Vec<(f64, f64, f64)> = points
        .iter()
        .enumerate()
        .map(|(i, &(t, v))| {
            let end = points.get(i + 1).map_or(period.to, |p| p.0);
            (x_of(t, period), x_of(end, period), v)
        })
        .collect();
    let content = html! {
        @for (x0, x1, v) in &bands {
            // Colours by class: the page's CSP admits no inline style.
            rect class={ "state s" ((*v as i64 - min).rem_euclid(12)) } x=(format!("{x0:.1}")) y="20"
                width=(format!("{:.1}", (x1 - x0).max(0.5))) height="50" data-state=(v) {}
            @if x1 - x0 > 8.0 * name(*v).chars().count() as f64 {
                text.state-name x=(format!("{:.1}", x0 + 4.0)) y="50" { (name(*v)) }
            }
        }
    };
    frame(period, H, points, Some((min, names)), l, content)
}

pub(super) async fn history_page(
    State(app): State<Arc<AppState>>,
    who: SignedIn,
    Path(id): Path<String>,
    Query(q): Query<HistoryQuery>,
) -> Response {
    let l = who.locale;
    let (mplexes, series, period, _) = match shown(&app, &who, &id, &q).await {
        Ok(s) => s,
        Err(r) => return r,
    };
    let described = describe(&app, &id, &mplexes, l).await;
    let list: Vec<String> = series.iter().map(|s| s.mplex.clone()).collect();
    let list = list.join(",");
    let ranges = [
        (10u32, "10 min"),
        (60, "1 h"),
        (360, "6 h"),
        (1440, "24 h"),
        (10080, "7 d"),
    ];
    let link = |p: &Period| format!("{}/history?{}", lift_path(&id), p.query(&list));
    let charts = html! {
        section #charts data-live=[period.minutes.map(|_| list.as_str())] {
            @for (s, d) in series.iter().zip(&described) {
                (figure(s, d, &period, l))
            }
        }
    };
    let title = described
        .iter()
        .map(|d| d.name.as_str())
        .collect::<Vec<_>>()
        .join(", ");
    let body = html! {
        h1 { (l.fill("History of {} on", &[&title])) " " a href=(lift_path(&id)) { (id) } }
        p.ranges {
            @for (m, label) in ranges {
                @let p = Period { from: 0, to: 0, minutes: Some(m) };
                a.current[period.minutes == Some(m)] href=(link(&p)) { (label) }
            }
        }
        p.muted.zone {}
        p {
            a.csv href={ (lift_path(&id)) "/history.csv?" (period.query(&list)) } download {
                (l.t("CSV of these values"))
            }
        }
        (charts)
        p.muted { (l.t("Drag across a chart to zoom in.")) }
    };
    layout(
        &l.fill("History {}", &[&list]),
        who.viewer(),
        Some(&id),
        body,
    )
    .into_response()
}

/// A stored value in words where the object is a choice.
fn state_name(d: &Described, value: &str) -> String {
    let named = d.states.as_ref().and_then(|(min, names)| {
        let v: i64 = value.trim().parse().ok()?;
        names.get(usize::try_from(v - min).ok()?).cloned()
    });
    named.unwrap_or_else(|| value.to_owned())
}

/// One object's chart with its name, unit and last value.
fn figure(s: &Series, d: &Described, period: &Period, l: Locale) -> Markup {
    let buckets = &s.history.buckets;
    let points = last_numbers(buckets);
    let count: i64 = buckets.iter().map(|b| b.count).sum();
    html! {
        figure.series data-series=(s.mplex) {
            figcaption {
                strong { (d.name) }
                @if !d.unit.is_empty() { " [" (d.unit) "]" }
                " " code { (s.mplex) }
            }
            p.summary {
                (l.fill("{} values, last ", &[&count]))
                @if let Some(b) = buckets.last() {
                    (state_name(d, &b.last)) (l.t(" at ")) (time(b.last_at, l))
                } @else {
                    "—"
                }
            }
            @if points.is_empty() {
                p.muted {
                    (l.t("No stored numeric values in this period. Values are stored while the gateway pushes them (the dashboard's objects, or a subscription)."))
                }
            } @else if let Some((min, names)) = &d.states {
                (state_chart(&points, period, (*min, names), l))
            } @else {
                (line_chart(buckets, s.history.width, period, d.unit, l))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_period_beyond_what_the_page_shows_is_the_last_hour() {
        let query = |from, to| HistoryQuery {
            mplex: "0x652001".into(),
            minutes: None,
            from: Some(from),
            to: Some(to),
        };
        for (from, to) in [
            (i64::MIN, i64::MAX),
            (-5, 10),
            (0, i64::MAX),
            (i64::MAX - 1, i64::MAX),
        ] {
            let p = Period::of(&query(from, to));
            assert_eq!(p.minutes, Some(60), "{from}..{to}");
            assert_eq!(p.to - p.from, 3_600_000);
        }
        let p = Period::of(&query(1_000, 2_000));
        assert_eq!((p.from, p.to, p.minutes), (1_000, 2_000, None));
    }

    /// A download's name never carries the gateway's quotes, semicolons or a path.
    #[test]
    fn download_names_are_sanitised() {
        let header = attachment("1050-4096-Q\";filename*=UTF-8''evil.html;x=\"-0x652001.csv");
        assert_eq!(
            header,
            "attachment; filename=\"1050-4096-Q__filename__UTF-8__evil.html_x__-0x652001.csv\"; \
             filename*=UTF-8''1050-4096-Q__filename__UTF-8__evil.html_x__-0x652001.csv"
        );
        assert_eq!(
            header.matches(';').count(),
            2,
            "two parameters alone: {header}"
        );
        assert_eq!(header.matches('"').count(), 2, "{header}");
    }

    fn hour() -> Period {
        Period {
            from: 0,
            to: 1000,
            minutes: None,
        }
    }

    #[test]
    fn csv_times_are_iso_8601_utc() {
        assert_eq!(iso(951_782_400_123), "2000-02-29T00:00:00.123Z");
        assert_eq!(iso(0), "1970-01-01T00:00:00.000Z");
    }

    fn bucket(at: i64, values: &[f64]) -> Bucket {
        let mut b = Bucket::of(at, at, &values[0].to_string());
        for (i, v) in values.iter().enumerate().skip(1) {
            b.merge(&Bucket::of(at, at + i as i64, &v.to_string()));
        }
        b
    }

    #[test]
    fn line_chart_steps_between_values_and_names_the_unit() {
        let buckets = [bucket(0, &[1.0]), bucket(500, &[3.0])];
        let svg = line_chart(&buckets, 500, &hour(), "mm", Locale::En).into_string();
        let points = svg
            .split("class=\"line\" points=\"")
            .nth(1)
            .unwrap()
            .split('"')
            .next()
            .unwrap();
        assert_eq!(points.split(' ').count(), 4, "{points}");
        assert!(svg.contains(">3 mm<"), "{svg}");
        assert!(
            !svg.contains("class=\"band\""),
            "one value a bucket: no band"
        );
    }

    #[test]
    fn a_bucket_of_many_values_is_a_band_from_its_smallest_to_its_largest() {
        let buckets = [bucket(0, &[5.0, -2.0, 9.0, 4.0]), bucket(500, &[1.0])];
        let svg = line_chart(&buckets, 500, &hour(), "", Locale::En).into_string();
        assert_eq!(svg.matches("class=\"band\"").count(), 1, "{svg}");
        assert!(svg.contains(">9 <") && svg.contains(">-2 <"), "{svg}");
    }

    #[test]
    fn state_chart_has_a_band_per_stretch_with_its_name() {
        let names = ["idle".to_owned(), "doors cycling".to_owned()];
        let svg =
            state_chart(&[(0, 1.0), (500, 2.0)], &hour(), (1, &names), Locale::En).into_string();
        assert_eq!(svg.matches("<rect class=\"state s").count(), 2, "{svg}");
        assert!(
            svg.contains(">idle<") && svg.contains(">doors cycling<"),
            "{svg}"
        );
        assert!(svg.contains("data-labels="), "the hover names the states");
    }

    #[test]
    fn a_period_is_the_last_minutes_or_fixed() {
        let q = |minutes, from, to| HistoryQuery {
            mplex: String::new(),
            minutes,
            from,
            to,
        };
        let last = Period::of(&q(Some(10), None, None));
        assert_eq!(last.to - last.from, 600_000);
        assert_eq!(last.query("0x652001"), "mplex=0x652001&minutes=10");
        let fixed = Period::of(&q(None, Some(1000), Some(5000)));
        assert_eq!((fixed.from, fixed.to, fixed.minutes), (1000, 5000, None));
        assert_eq!(fixed.query("a,b"), "mplex=a%2Cb&from=1000&to=5000");
        let backwards = Period::of(&q(None, Some(5000), Some(1000)));
        assert_eq!(
            backwards.minutes,
            Some(60),
            "a backward range is the last hour"
        );
    }
}
