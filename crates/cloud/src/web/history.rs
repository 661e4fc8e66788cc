//! The history page: the stored values of one object over a period, as an SVG step chart
//! drawn by the portal.

use std::sync::Arc;

use axum::extract::{Path, Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use maud::{html, Markup};
use serde::Deserialize;

use super::i18n::Locale;
use super::page::{layout, problem, time, unavailable, utc};
use super::{owned, SignedIn};
use crate::api::App;
use crate::store;

#[derive(Deserialize)]
pub(super) struct HistoryQuery {
    mplex: String,
    /// The period shown, ending now.
    minutes: Option<u32>,
}

/// An SVG step chart of `points` (ms, value) between `from` and `to`.
fn chart(points: &[(i64, f64)], from: i64, to: i64, l: Locale) -> Markup {
    const W: f64 = 800.0;
    const H: f64 = 280.0;
    const LEFT: f64 = 70.0;
    const BOTTOM: f64 = 30.0;
    let lo = points.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
    let hi = points.iter().map(|p| p.1).fold(f64::NEG_INFINITY, f64::max);
    let (lo, hi) = if (hi - lo).abs() < f64::EPSILON {
        (lo - 1.0, hi + 1.0)
    } else {
        (lo, hi)
    };
    let x = |t: i64| LEFT + (t - from) as f64 / (to - from).max(1) as f64 * (W - LEFT - 10.0);
    let y = |v: f64| 10.0 + (hi - v) / (hi - lo) * (H - BOTTOM - 10.0);
    let mut path = Vec::with_capacity(points.len() * 2 + 1);
    let mut previous: Option<f64> = None;
    for &(t, v) in points {
        if let Some(p) = previous {
            path.push(format!("{:.1},{:.1}", x(t), y(p)));
        }
        path.push(format!("{:.1},{:.1}", x(t), y(v)));
        previous = Some(v);
    }
    if let Some(p) = previous {
        path.push(format!("{:.1},{:.1}", x(to), y(p)));
    }
    let (bottom, right, label_x, label_y) = (H - BOTTOM, W - 10.0, LEFT - 6.0, H - 8.0);
    html! {
        svg.chart viewBox={ "0 0 " (W) " " (H) } role="img" aria-label=(l.t("history chart"))
            data-from=(from) data-to=(to) data-left=(LEFT) data-right=(W - 10.0)
            data-points=(points.iter().map(|(t, v)| format!("{t}:{v}")).collect::<Vec<_>>().join(",")) {
            line x1=(LEFT) y1="10" x2=(LEFT) y2=(bottom) class="axis" {}
            line x1=(LEFT) y1=(bottom) x2=(right) y2=(bottom) class="axis" {}
            text x=(label_x) y="16" class="label" text-anchor="end" { (hi) }
            text x=(label_x) y=(bottom) class="label" text-anchor="end" { (lo) }
            text x=(LEFT) y=(label_y) class="label" data-ms=(from) { (utc(from)) }
            text x=(right) y=(label_y) class="label" text-anchor="end" data-ms=(to) { (utc(to)) }
            polyline class="line" points=(path.join(" ")) {}
            // The script's hover: a cursor line and the nearest value with its time.
            line.cursor x1="0" y1="10" x2="0" y2=(bottom) visibility="hidden" {}
            text.hover x=(LEFT + 6.0) y="24" {}
        }
    }
}

/// The stored values a history page or its CSV shows.
struct Shown {
    mplex: String,
    minutes: u32,
    from: i64,
    to: i64,
    rows: Vec<(i64, String)>,
}

/// The values of `q` on lift `id`, or the page that says why not.
async fn shown(app: &App, who: &SignedIn, id: &str, q: &HistoryQuery) -> Result<Shown, Response> {
    let l = who.locale;
    owned(app, who, id).await?;
    let mplex = match app.names.resolve(&q.mplex) {
        Ok(mplex) => mplex.to_string(),
        Err(e) => {
            let message = l.fill("mplex: {}", &[&e]);
            return Err(problem(StatusCode::BAD_REQUEST, who.viewer(), &message));
        }
    };
    let minutes = q.minutes.unwrap_or(60).clamp(1, 31 * 24 * 60);
    let to = store::now_ms();
    let from = to - i64::from(minutes) * 60_000;
    match app.store.history(id, &mplex, from, to).await {
        Ok(rows) => Ok(Shown {
            mplex,
            minutes,
            from,
            to,
            rows,
        }),
        Err(e) => Err(unavailable(e, who.viewer())),
    }
}

/// `GET /lifts/{id}/history.csv?mplex=&minutes=`: what the page shows, as CSV (RFC 4180) with
/// UTC times (ISO 8601).
pub(super) async fn history_csv(
    State(app): State<Arc<App>>,
    who: SignedIn,
    Path(id): Path<String>,
    Query(q): Query<HistoryQuery>,
) -> Response {
    let shown = match shown(&app, &who, &id, &q).await {
        Ok(s) => s,
        Err(r) => return r,
    };
    let mut csv = String::from("time,value\r\n");
    for (at, value) in &shown.rows {
        let quoted = if value.contains([',', '"', '\r', '\n']) {
            format!("\"{}\"", value.replace('"', "\"\""))
        } else {
            value.clone()
        };
        csv.push_str(&format!("{},{quoted}\r\n", iso(*at)));
    }
    let file = format!("{id}-{}.csv", shown.mplex);
    (
        [
            (header::CONTENT_TYPE, "text/csv; charset=utf-8".to_owned()),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{file}\""),
            ),
        ],
        csv,
    )
        .into_response()
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

pub(super) async fn history_page(
    State(app): State<Arc<App>>,
    who: SignedIn,
    Path(id): Path<String>,
    Query(q): Query<HistoryQuery>,
) -> Response {
    let l = who.locale;
    let Shown {
        mplex,
        minutes,
        from,
        to,
        rows,
    } = match shown(&app, &who, &id, &q).await {
        Ok(s) => s,
        Err(r) => return r,
    };
    let points: Vec<(i64, f64)> = rows
        .iter()
        .filter_map(|(at, v)| v.trim().parse::<f64>().ok().map(|v| (*at, v)))
        .collect();
    let ranges = [
        (10u32, "10 min"),
        (60, "1 h"),
        (360, "6 h"),
        (1440, "24 h"),
        (10080, "7 d"),
    ];
    let body = html! {
        h1 { (l.fill("History of {} on", &[&mplex])) " " a href={ "/lifts/" (id) } { (id) } }
        p.ranges {
            @for (m, label) in ranges {
                a.current[m == minutes] href={ "/lifts/" (id) "/history?mplex=" (mplex) "&minutes=" (m) } {
                    (label)
                }
            }
        }
        p.summary {
            (l.fill("{} values, last ", &[&points.len()]))
            @if let Some((at, v)) = points.last() {
                (v) (l.t(" at ")) (time(*at, l))
            } @else {
                "—"
            }
        }
        p.muted.zone {}
        @if !points.is_empty() {
            p { a.csv href={ "/lifts/" (id) "/history.csv?mplex=" (mplex) "&minutes=" (minutes) } download { (l.t("CSV of these values")) } }
        }
        @if points.is_empty() {
            p.muted {
                (l.t("No stored numeric values in this period. Values are stored while the gateway pushes them (the dashboard's objects, or a subscription)."))
            }
        } @else {
            (chart(&points, from, to, l))
        }
    };
    layout(&l.fill("History {}", &[&mplex]), who.viewer(), None, body).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_times_are_iso_8601_utc() {
        assert_eq!(iso(951_782_400_123), "2000-02-29T00:00:00.123Z");
        assert_eq!(iso(0), "1970-01-01T00:00:00.000Z");
    }

    #[test]
    fn chart_steps_between_values() {
        let svg = chart(&[(0, 1.0), (500, 3.0)], 0, 1000, Locale::En).into_string();
        assert!(svg.contains("<polyline"), "{svg}");
        // Three points per change: the old level to the change, then the new one to the end.
        let points = svg
            .split("class=\"line\" points=\"")
            .nth(1)
            .unwrap()
            .split('"')
            .next()
            .unwrap();
        assert_eq!(points.split(' ').count(), 4, "{points}");
    }
}
