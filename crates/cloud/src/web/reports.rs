//! The monthly report (docs/PORTAL.md §Monthly report): an account's month against the
//! availability it promises, its faults by kind, the three months before, and every lift, the
//! least available first — one block per lift, so a printout (the print style sheet drops
//! the navigation) reads as the service company's report to the building owner.

use std::sync::Arc;

use axum::extract::{Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use maud::{html, Markup};
use serde::Deserialize;

use super::i18n::Locale;
use super::page::{layout, lift_path, problem, unavailable};
use super::SignedIn;
use crate::insights::{self, Month};
use crate::state::AppState;
use cloud_types::insights::{LiftFigures, Status};

#[derive(Deserialize)]
pub(super) struct ReportQuery {
    /// `YYYY-MM`; default: the last complete month.
    month: Option<String>,
}

/// A share as a percentage, `99.53 %`; a dash for none.
pub(super) fn percent(share: Option<f64>) -> String {
    share.map_or_else(|| "–".into(), |s| format!("{:.2} %", s * 100.0))
}

/// Seconds as hours, `12.5 h`; a dash for none.
fn hours(seconds: Option<f64>) -> String {
    seconds.map_or_else(|| "–".into(), |s| format!("{:.1} h", s / 3600.0))
}

fn count(n: Option<u64>) -> String {
    n.map_or_else(|| "–".into(), |n| n.to_string())
}

/// One lift's block.
fn lift_block(f: &LiftFigures, target: f64, l: Locale) -> Markup {
    let missed = f.availability.is_some_and(|a| a < target);
    let kinds: Vec<String> = f
        .faults_by_kind
        .iter()
        .map(|(code, n)| format!("{code} × {n}"))
        .collect();
    html! {
        section.lift-report {
            h3 {
                a href=(lift_path(&f.lift)) { (f.lift) } " "
                span class=(if missed { "fault" } else { "ok" }) { (percent(f.availability)) }
            }
            dl.figures {
                dt { (l.t("In service")) } dd { (hours(Some(f.in_service_s))) }
                dt { (l.t("Out of service")) } dd { (hours(Some(f.out_of_service_s))) }
                dt { (l.t("Gateway offline")) } dd { (hours(Some(f.offline_s))) }
                dt { (l.t("Unknown")) } dd { (hours(Some(f.unknown_s))) }
                dt { (l.t("Faults")) } dd { (f.faults) @if !kinds.is_empty() { " (" (kinds.join(", ")) ")" } }
                dt { (l.t("Trips")) } dd { (count(f.trips)) }
                dt { (l.t("Faults per 1000 trips")) } dd { (f.faults_per_1000_trips.map_or_else(|| "–".into(), |v| format!("{v:.2}"))) }
                dt { abbr title=(l.t("mean time between failures")) { "MTBF" } } dd { (hours(f.mtbf_s)) }
                dt { abbr title=(l.t("mean time to repair")) { "MTTR" } } dd { (hours(f.mttr_s)) }
                dt { (l.t("Door cycles")) } dd { (count(f.door_cycles)) }
                dt { (l.t("Reopenings")) } dd { (count(f.reopenings)) }
            }
        }
    }
}

/// A lift's last days on the lift page: its availability, time out of service and faults, and
/// its statuses as a bar, out-of-service spans in their own colour (an SVG: the page's
/// Content-Security-Policy allows no inline style).
pub(super) fn recent(
    f: &LiftFigures,
    spans: &[(i64, i64, Status)],
    from: i64,
    to: i64,
    l: Locale,
) -> Markup {
    let width = (to - from).max(1) as f64;
    let status_text = |s: Status| match s {
        Status::InService => l.t("In service"),
        Status::OutOfService => l.t("Out of service"),
        Status::Offline => l.t("Gateway offline"),
        Status::Unknown => l.t("Unknown"),
    };
    html! {
        section #availability {
            h2 { (l.t("Availability (30 days)")) }
            dl.figures {
                dt { (l.t("Availability")) } dd { (percent(f.availability)) }
                dt { (l.t("Out of service")) } dd { (hours(Some(f.out_of_service_s))) }
                dt { (l.t("Gateway offline")) } dd { (hours(Some(f.offline_s))) }
                dt { (l.t("Faults")) } dd { (f.faults) }
            }
            svg.availability viewBox="0 0 1000 10" preserveAspectRatio="none" role="img"
                aria-label=(l.t("Availability (30 days)")) {
                @for (start, end, status) in spans {
                    rect class=(status.name()) x=(format!("{:.2}", (start - from) as f64 / width * 1000.0))
                        width=(format!("{:.2}", (end - start) as f64 / width * 1000.0)) y="0" height="10" {
                        title { (status_text(*status)) ": " (super::page::utc(*start)) " – " (super::page::utc(*end)) }
                    }
                }
            }
            p.legend.muted {
                @for status in Status::ALL {
                    span class=(status.name()) { "■ " (status_text(status)) } " "
                }
            }
        }
    }
}

pub(super) async fn reports_page(
    State(app): State<Arc<AppState>>,
    who: SignedIn,
    Query(q): Query<ReportQuery>,
) -> Response {
    let l = who.locale;
    let Some(month) = Month::asked(q.month.as_deref()) else {
        let message = l.t("A month is written YYYY-MM.");
        return problem(StatusCode::BAD_REQUEST, who.viewer(), message);
    };
    let account = &who.session.operator.account;
    let report = match insights::monthly(&app.store, &app.insights, account, month).await {
        Ok(r) => r,
        Err(e) => return unavailable(e, who.viewer()),
    };
    let met = report.availability.map(|a| a >= report.target);
    let link = |m: Month| format!("/reports?month={m}");
    let title = l.fill("Monthly report {}", &[&report.month]);
    let body = html! {
        h1 { (title) }
        p.months.no-print {
            a href=(link(month.previous())) { (l.t("← previous month")) } " "
            a href=(link(month.next())) { (l.t("next month →")) }
        }
        section.report-summary {
            dl.figures {
                dt { (l.t("Account")) } dd { (report.account) }
                dt { (l.t("Availability")) }
                dd {
                    (percent(report.availability)) " "
                    @match met {
                        Some(true) => span.ok { (l.t("target met")) },
                        Some(false) => span.fault { (l.t("target missed")) },
                        None => span.muted { (l.t("no data")) },
                    }
                }
                dt { (l.t("Target")) } dd { (percent(Some(report.target))) }
                dt { (l.t("Lifts")) } dd { (report.lifts.len()) }
            }
            h2 { (l.t("The months before")) }
            table.trend {
                thead { tr { th { (l.t("Month")) } th { (l.t("Availability")) } } }
                tbody {
                    @for m in &report.trend {
                        tr { td { a href={ "/reports?month=" (m.month) } { (m.month) } } td { (percent(m.availability)) } }
                    }
                    tr.current { td { (report.month) } td { (percent(report.availability)) } }
                }
            }
            h2 { (l.t("Faults by kind")) }
            @if report.faults_by_kind.is_empty() {
                p.ok { (l.t("No fault.")) }
            } @else {
                table.faults {
                    thead { tr { th { (l.t("EMCY code")) } th { (l.t("Faults")) } } }
                    tbody {
                        @for (code, n) in &report.faults_by_kind {
                            tr { td { code { (code) } } td { (n) } }
                        }
                    }
                }
            }
        }
        h2 { (l.t("Lifts, the least available first")) }
        @for f in &report.lifts {
            (lift_block(f, report.target, l))
        }
    };
    layout(&title, who.viewer(), None, body).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn figures_read_as_people_write_them() {
        assert_eq!(percent(Some(0.99534)), "99.53 %");
        assert_eq!(percent(None), "–");
        assert_eq!(hours(Some(45_000.0)), "12.5 h");
        assert_eq!(count(None), "–");
    }
}
