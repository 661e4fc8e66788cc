//! The fleet page: every lift of the account with one coloured state (in service, out of
//! service, faults, offline), when a value last arrived (or the lift was last seen), its most
//! severe active alarm and its active faults; counts per state, filters, sort, search and
//! pages, and each lift's availability over the last 30 days (docs/PORTAL.md §Availability;
//! computed at most once a minute per account). The condition of connected lifts comes from the
//! registry (their pushes), not the database: the page costs one lookup per lift. The script
//! refreshes the table.

use std::collections::HashMap;
use std::sync::Arc;

use axum::extract::{Query, State};
use axum::response::{IntoResponse, Response};
use maud::{html, Markup};
use serde::Deserialize;

use super::alarms::severity_badge;
use super::i18n::Locale;
use super::page::{layout, lift_path, time, unavailable};
use super::SignedIn;
use crate::gateways::LiftStatus;
use crate::state::AppState;
use cloud_types::alarms::Alarm;
use cloud_types::lifts::shown_id;
use cloud_types::lifts::LiftRecord;

/// Lifts per page.
const PAGE: usize = 100;

/// A lift's state at a glance, worst last.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub(super) enum FleetState {
    InService,
    OutOfService,
    Faults,
    Offline,
}

impl FleetState {
    const ALL: [FleetState; 4] = [
        FleetState::InService,
        FleetState::OutOfService,
        FleetState::Faults,
        FleetState::Offline,
    ];

    /// Offline first; a fault (error register or an active alarm) outweighs out of service.
    fn of(status: Option<LiftStatus>, alarm: Option<&Alarm>) -> FleetState {
        match status {
            None => FleetState::Offline,
            Some(s) if s.faulty() || alarm.is_some() => FleetState::Faults,
            Some(s) if s.out_of_service() => FleetState::OutOfService,
            Some(_) => FleetState::InService,
        }
    }

    fn text(self) -> &'static str {
        match self {
            FleetState::InService => "in service",
            FleetState::OutOfService => "out of service",
            FleetState::Faults => "faults",
            FleetState::Offline => "offline",
        }
    }

    fn key(self) -> &'static str {
        match self {
            FleetState::InService => "in-service",
            FleetState::OutOfService => "out-of-service",
            FleetState::Faults => "faults",
            FleetState::Offline => "offline",
        }
    }

    fn badge(self, l: Locale) -> Markup {
        html! { span.badge.{ "state-" (self.key()) } { (l.t(self.text())) } }
    }
}

/// The bits of the error register (CiA 301 §7.5.2.2), bit 0 first; the script shows them too.
pub(super) const ERROR_BITS: [&str; 8] = [
    "generic",
    "current",
    "voltage",
    "temperature",
    "communication",
    "device profile",
    "reserved",
    "manufacturer",
];

/// The fault column: the error register's bits and an out-of-service lift state.
fn faults(status: Option<LiftStatus>, l: Locale) -> Markup {
    let Some(status) = status.filter(|s| s.error_register.is_some() || s.lift_state.is_some())
    else {
        return html! { span.muted { (l.t("no data")) } };
    };
    let register = status.error_register.unwrap_or(0);
    let mut found: Vec<&str> = ERROR_BITS
        .iter()
        .enumerate()
        .filter(|(i, _)| register & (1 << i) != 0)
        .map(|(_, name)| l.t(name))
        .collect();
    if status.out_of_service() {
        found.push(l.t("out of service"));
    }
    html! {
        @if found.is_empty() {
            span.ok { (l.t("none")) }
        } @else {
            span.fault { (found.join(", ")) }
        }
    }
}

/// How the table is ordered.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub(super) enum Sort {
    /// By lift id.
    #[default]
    Lift,
    /// By lift number.
    Number,
    /// Worst state first.
    State,
    /// Longest silent first.
    Seen,
}

impl Sort {
    /// Its `?sort=` value.
    fn key(self) -> &'static str {
        match self {
            Sort::Lift => "lift",
            Sort::Number => "number",
            Sort::State => "state",
            Sort::Seen => "seen",
        }
    }
}

#[derive(Deserialize)]
pub(super) struct FleetQuery {
    /// 1-based page.
    page: Option<usize>,
    /// Part of a lift's id or lift number.
    q: Option<String>,
    /// Only lifts in this state.
    show: Option<FleetState>,
    sort: Option<Sort>,
}

/// One lift as the table shows it.
struct Row<'a> {
    lift: &'a LiftRecord,
    status: Option<LiftStatus>,
    state: FleetState,
    /// A value's arrival for a connected lift, else the end of its last connection.
    seen: i64,
}

pub(super) async fn fleet(
    State(app): State<Arc<AppState>>,
    who: SignedIn,
    Query(query): Query<FleetQuery>,
) -> Response {
    let (session, l) = (&who.session, who.locale);
    let domain = &session.operator.account.domain;
    let (all, worst, available) = match tokio::join!(
        app.store.lifts(domain),
        app.store.worst_alarms(domain),
        app.recent.of(&app.store, domain)
    ) {
        (Ok(l), Ok(w), Ok(a)) => (l, w, a),
        (Err(e), _, _) | (_, Err(e), _) | (_, _, Err(e)) => return unavailable(e, who.viewer()),
    };
    let needle = query.q.as_deref().unwrap_or("").trim().to_lowercase();
    let mut counts: HashMap<FleetState, usize> = HashMap::new();
    let mut rows: Vec<Row> = Vec::new();
    for lift in &all {
        let status = app.registry.status(&lift.id);
        let state = FleetState::of(status, worst.get(&lift.id));
        *counts.entry(state).or_default() += 1;
        let found = needle.is_empty()
            || lift.id.to_lowercase().contains(&needle)
            || lift.liftnum.to_lowercase().contains(&needle);
        if found && query.show.is_none_or(|s| s == state) {
            let seen = match status {
                Some(s) if s.last_value > 0 => s.last_value,
                _ => lift.last_seen,
            };
            rows.push(Row {
                lift,
                status,
                state,
                seen,
            });
        }
    }
    let sort = query.sort.unwrap_or_default();
    match sort {
        Sort::Lift => rows.sort_by(|a, b| a.lift.id.cmp(&b.lift.id)),
        Sort::Number => rows.sort_by(|a, b| a.lift.liftnum.cmp(&b.lift.liftnum)),
        Sort::State => rows.sort_by(|a, b| b.state.cmp(&a.state).then(a.lift.id.cmp(&b.lift.id))),
        Sort::Seen => rows.sort_by_key(|r| r.seen),
    }
    let pages = rows.len().div_ceil(PAGE).max(1);
    let page = query.page.unwrap_or(1).clamp(1, pages);
    let link = |page: usize, show: Option<FleetState>, sort: Sort| {
        let mut q: Vec<(&str, String)> = vec![("page", page.to_string())];
        if !needle.is_empty() {
            q.push(("q", needle.clone()));
        }
        if let Some(s) = show {
            q.push(("show", s.key().into()));
        }
        if sort != Sort::Lift {
            q.push(("sort", sort.key().into()));
        }
        format!("/?{}", serde_urlencoded::to_string(q).unwrap_or_default())
    };
    let heading = |label: &'static str, by: Sort| {
        html! {
            th { a.sort.current[sort == by] href=(link(1, query.show, by)) { (l.t(label)) } }
        }
    };
    let body = html! {
        h1 { (l.t("Fleet")) }
        @if all.is_empty() {
            // The domain token admits gateways into the account: for its administrators only.
            @if session.operator.may(cloud_types::users::Role::Admin) {
                p { (l.fill("No lift of domain {} has connected yet.", &[&session.operator.account.domain])) }
            } @else {
                p { (l.t("No lift has connected yet.")) }
            }
        } @else {
            p.summary {
                a.current[query.show.is_none()] href=(link(1, None, sort)) {
                    @if all.len() == 1 {
                        (l.fill("{} lift", &[&all.len()]))
                    } @else {
                        (l.fill("{} lifts", &[&all.len()]))
                    }
                }
                @for state in FleetState::ALL {
                    " · "
                    a.current[query.show == Some(state)] data-count=(state.key())
                        href=(link(1, Some(state), sort)) {
                        (counts.get(&state).copied().unwrap_or(0)) " " (l.t(state.text()))
                    }
                }
            }
            form.read method="get" {
                input name="q" placeholder=(l.t("lift id or number")) value=(needle);
                @if let Some(s) = query.show { input type="hidden" name="show" value=(s.key()); }
                button { (l.t("Find")) }
            }
            @if rows.is_empty() {
                p.muted.none { (l.t("No lift matches.")) }
            } @else {
                table.fleet {
                    thead { tr {
                        (heading("Lift", Sort::Lift)) (heading("Lift number", Sort::Number))
                        (heading("State", Sort::State)) (heading("Last value / seen", Sort::Seen))
                        th { (l.t("Alarm")) } th { (l.t("Active faults")) }
                        th { (l.t("Availability (30 days)")) }
                    } }
                    tbody {
                        @for row in rows.iter().skip((page - 1) * PAGE).take(PAGE) {
                            tr data-state=(row.state.key()) {
                                td { a href=(lift_path(&row.lift.id)) { (shown_id(&row.lift.id)) } }
                                td { (row.lift.liftnum) }
                                td { (row.state.badge(l)) }
                                td { (time(row.seen, l)) }
                                td.alarm {
                                    @if let Some(a) = worst.get(&row.lift.id) {
                                        (severity_badge(a.severity, l)) " " (a.text)
                                    } @else {
                                        span.ok { (l.t("none")) }
                                    }
                                }
                                td { (faults(row.status, l)) }
                                td.availability {
                                    (super::reports::percent(available.get(&row.lift.id).copied().flatten()))
                                }
                            }
                        }
                    }
                }
                p.ranges {
                    (l.fill("page {} of {}", &[&page, &pages])) " "
                    @if page > 1 { a href=(link(page - 1, query.show, sort)) { (l.t("← previous")) } }
                    @if page < pages { a href=(link(page + 1, query.show, sort)) { (l.t("next →")) } }
                }
            }
        }
    };
    layout(l.t("Fleet"), who.viewer(), None, body).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fault_column_and_state() {
        let text = |s: Option<LiftStatus>| faults(s, Locale::En).into_string();
        assert!(text(None).contains("no data"));
        let mut status = LiftStatus {
            error_register: Some(0),
            ..LiftStatus::default()
        };
        assert!(text(Some(status)).contains("none"));
        assert_eq!(FleetState::of(Some(status), None), FleetState::InService);
        status.lift_state = Some(4);
        assert_eq!(FleetState::of(Some(status), None), FleetState::OutOfService);
        status.error_register = Some(129);
        assert!(text(Some(status)).contains("generic, manufacturer, out of service"));
        assert_eq!(FleetState::of(Some(status), None), FleetState::Faults);
        assert_eq!(FleetState::of(None, None), FleetState::Offline);
        assert!(FleetState::Offline > FleetState::Faults, "worst last");
    }
}
