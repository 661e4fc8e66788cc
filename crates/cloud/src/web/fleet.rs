//! The fleet page: every lift of the account with its online state, when it was last seen, its
//! most severe active alarm and its active faults, paged and searchable; the script refreshes
//! the table.

use std::collections::HashMap;
use std::sync::Arc;

use axum::extract::{Query, State};
use axum::response::{IntoResponse, Response};
use maud::{html, Markup};
use serde::Deserialize;

use super::alarms::severity_badge;
use super::page::{layout, online_badge, time};
use super::SignedIn;
use crate::api::App;
use crate::store::LiftRecord;

/// The error register (CiA 301 §7.5.2.2) and the lift state (our 5024h): the fault column.
pub(super) const ERROR_REGISTER: &str = "0x100100";
pub(super) const LIFT_STATE: &str = "0x502400";

/// Lifts per page.
const PAGE: usize = 100;

/// The fault column: the error register's bits and an out-of-service lift state, from the
/// newest stored values.
fn faults(latest: &HashMap<String, (i64, String)>) -> Markup {
    const BITS: [&str; 8] = [
        "generic",
        "current",
        "voltage",
        "temperature",
        "communication",
        "device profile",
        "reserved",
        "manufacturer",
    ];
    let value = |key: &str| latest.get(key).and_then(|(_, v)| v.parse::<u8>().ok());
    let (register, state) = (value(ERROR_REGISTER), value(LIFT_STATE));
    if register.is_none() && state.is_none() {
        return html! { span.muted { "no data" } };
    }
    let mut found: Vec<&str> = BITS
        .iter()
        .enumerate()
        .filter(|(i, _)| register.is_some_and(|r| r & (1 << i) != 0))
        .map(|(_, name)| *name)
        .collect();
    if state == Some(4) {
        found.push("out of service");
    }
    html! {
        @if found.is_empty() {
            span.ok { "none" }
        } @else {
            span.fault { (found.join(", ")) }
        }
    }
}

#[derive(Deserialize)]
pub(super) struct FleetQuery {
    /// 1-based page.
    page: Option<usize>,
    /// Part of a lift's id or lift number.
    q: Option<String>,
}

pub(super) async fn fleet(
    State(app): State<Arc<App>>,
    SignedIn(session): SignedIn,
    Query(query): Query<FleetQuery>,
) -> Response {
    let all = match app.store.lifts(&session.account.domain).await {
        Ok(l) => l,
        Err(e) => return e.into(),
    };
    let total = all.len();
    let online_count = all.iter().filter(|l| app.registry.online(&l.id)).count();
    let needle = query.q.as_deref().unwrap_or("").trim().to_lowercase();
    let lifts: Vec<&LiftRecord> = all
        .iter()
        .filter(|l| {
            needle.is_empty()
                || l.id.to_lowercase().contains(&needle)
                || l.liftnum.to_lowercase().contains(&needle)
        })
        .collect();
    let pages = lifts.len().div_ceil(PAGE).max(1);
    let page = query.page.unwrap_or(1).clamp(1, pages);
    let worst = match app.store.worst_alarms(&session.account.domain).await {
        Ok(w) => w,
        Err(e) => return e.into(),
    };
    let watched = [ERROR_REGISTER.to_owned(), LIFT_STATE.to_owned()];
    let mut rows = Vec::new();
    for lift in lifts.iter().skip((page - 1) * PAGE).take(PAGE) {
        match app.store.latest(&lift.id, &watched).await {
            Ok(latest) => rows.push((lift, latest)),
            Err(e) => return e.into(),
        }
    }
    let link = |p: usize| {
        let query = serde_urlencoded::to_string([("page", p.to_string()), ("q", needle.clone())]);
        format!("/?{}", query.unwrap_or_default())
    };
    let body = html! {
        h1 { "Fleet" }
        @if total == 0 {
            p { "No lift of domain " code { (session.account.domain) } " has connected yet." }
        } @else {
            p.summary { (online_count) " of " (total) " lifts online" }
            form.read method="get" {
                input name="q" placeholder="lift id or number" value=(needle);
                button { "Find" }
            }
            table.fleet {
                thead { tr {
                    th { "Lift" } th { "Lift number" } th { "State" } th { "Last seen" }
                    th { "Alarm" } th { "Active faults" }
                } }
                tbody {
                    @for (lift, latest) in &rows {
                        tr {
                            td { a href={ "/lifts/" (lift.id) } { (lift.id) } }
                            td { (lift.liftnum) }
                            td { (online_badge(&lift.id, app.registry.online(&lift.id))) }
                            td { (time(lift.last_seen)) }
                            td.alarm {
                                @if let Some(a) = worst.get(&lift.id) {
                                    (severity_badge(a.severity)) " " (a.text)
                                } @else {
                                    span.ok { "none" }
                                }
                            }
                            td { (faults(latest)) }
                        }
                    }
                }
            }
            p.ranges {
                "page " (page) " of " (pages) " "
                @if page > 1 { a href=(link(page - 1)) { "← previous" } }
                @if page < pages { a href=(link(page + 1)) { "next →" } }
            }
        }
    };
    layout("Fleet", Some(&session), None, body).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fault_column() {
        let text = |l: &HashMap<String, (i64, String)>| faults(l).into_string();
        let mut latest = HashMap::new();
        assert!(text(&latest).contains("no data"));
        latest.insert(ERROR_REGISTER.to_owned(), (1, "0".to_owned()));
        assert!(text(&latest).contains("none"));
        latest.insert(ERROR_REGISTER.to_owned(), (1, "129".to_owned()));
        latest.insert(LIFT_STATE.to_owned(), (1, "4".to_owned()));
        assert!(text(&latest).contains("generic, manufacturer, out of service"));
    }
}
