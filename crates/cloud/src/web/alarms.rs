//! The alarms page — the account's active alarms, each with an acknowledge form (no script
//! needed; the session's CSRF token in the form), and the latest cleared ones — and the parts
//! the lift and fleet pages share: the alarm table, the severity badge, the event log.

use std::sync::Arc;

use axum::extract::{Form, Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Redirect, Response};
use maud::{html, Markup};
use nxg::msg::Event;
use serde::Deserialize;

use super::i18n::Locale;
use super::page::{layout, lift_path, problem, time, unavailable};
use super::SignedIn;
use crate::alarms::service::AckError;
use crate::state::AppState;
use cloud_store::AlarmFilter;
use cloud_types::alarms::{Alarm, Severity};
use cloud_types::lifts::shown_id;
use cloud_types::users::Role;

/// A severity as a coloured badge.
pub(super) fn severity_badge(severity: Severity, l: Locale) -> Markup {
    html! { span.badge.{ "sev-" (severity.name()) } { (l.t(severity.name())) } }
}

/// An RFC 3339 time as a local time on the page.
fn at(text: &str, l: Locale) -> Markup {
    time(nxg::msg::parse_time(text).unwrap_or(0), l)
}

/// Where an alarm is, in words.
fn place(alarm: &Alarm, l: Locale) -> String {
    match alarm.node {
        Some(p) => match p.id {
            Some(id) => l.fill("node {} (net {})", &[&id, &p.net]),
            None => l.fill("net {}", &[&p.net]),
        },
        None => l.t("gateway").into(),
    }
}

/// Alarms as a table; active ones not yet taken on have an acknowledge form that returns to
/// `back`.
pub(super) fn table(alarms: &[Alarm], who: &SignedIn, back: &str, lifts: bool) -> Markup {
    let l = who.locale;
    html! {
        table.alarms {
            thead { tr {
                th { (l.t("Severity")) } @if lifts { th { (l.t("Lift")) } } th { (l.t("Where")) }
                th { (l.t("Alarm")) } th { (l.t("Raised")) } th { (l.t("Acknowledged")) }
                th { (l.t("Cleared")) }
            } }
            tbody {
                @for a in alarms {
                    tr data-alarm=(a.id) {
                        td { (severity_badge(a.severity, l)) }
                        @if lifts { td { a href=(lift_path(&a.lift)) { (shown_id(&a.lift)) } } }
                        td { (place(a, l)) }
                        td { (a.text) }
                        td { (at(&a.raised, l)) }
                        td {
                            @if let Some(ack) = &a.acknowledged {
                                (ack.by) ", " (at(&ack.at, l))
                                @if !ack.comment.is_empty() { br; span.muted { (ack.comment) } }
                            } @else if who.session.operator.may(Role::Technician) {
                                form.ack method="post" action={ "/alarms/" (a.id) "/ack" } {
                                    input type="hidden" name="csrf" value=(who.session.csrf);
                                    input type="hidden" name="back" value=(back);
                                    input name="comment" placeholder=(l.t("comment")) maxlength="1000";
                                    button { (l.t("Acknowledge")) }
                                }
                            }
                        }
                        td {
                            @if let Some(c) = &a.cleared { (at(c, l)) } @else { span.fault { (l.t("active")) } }
                        }
                    }
                }
            }
        }
    }
}

/// A lift's bus events, newest first.
pub(super) fn event_log(events: &[Event], l: Locale) -> Markup {
    let node = |id: u8, net: u8| l.fill("node {} (net {})", &[&id, &net]);
    html! {
        table.events {
            thead { tr {
                th { (l.t("Time")) } th { (l.t("Type")) } th { (l.t("Where")) } th { (l.t("What")) }
            } }
            tbody {
                @for e in events.iter().rev() {
                    @match e {
                        Event::Emcy { node: n, time: t, code, register, text, .. } => tr {
                            td { (at(t, l)) } td { "EMCY" }
                            td { (node(n.id.get(), n.net)) }
                            td { (text) " " span.muted { (code) (l.t(", register ")) (register) } }
                        },
                        Event::State { node: n, time: t, state } => tr {
                            td { (at(t, l)) } td { (l.t("state")) }
                            td { (node(n.id.get(), n.net)) }
                            td { (state.name()) }
                        },
                        Event::Bus { net, time: t, state } => tr {
                            td { (at(t, l)) } td { (l.t("network")) } td { (l.fill("net {}", &[net])) }
                            td { (state.name()) }
                        },
                    }
                }
            }
        }
    }
}

pub(super) async fn alarms_page(State(app): State<Arc<AppState>>, who: SignedIn) -> Response {
    let l = who.locale;
    let domain = &who.session.operator.account.domain;
    let active = AlarmFilter {
        active: true,
        lift: None,
        limit: 1000,
    };
    let recent = AlarmFilter {
        active: false,
        lift: None,
        limit: 50,
    };
    let (active, recent) = match (
        app.store.alarms(domain, &active).await,
        app.store.alarms(domain, &recent).await,
    ) {
        (Ok(a), Ok(r)) => (a, r),
        (Err(e), _) | (_, Err(e)) => return unavailable(e, who.viewer()),
    };
    let cleared: Vec<Alarm> = recent.into_iter().filter(|a| !a.active()).collect();
    let body = html! {
        h1 { (l.t("Alarms")) }
        @if active.is_empty() {
            p.ok { (l.t("No active alarm.")) }
        } @else {
            p.summary { (l.fill("{} active", &[&active.len()])) }
            (table(&active, &who, "/alarms", true))
        }
        h2 { (l.t("Recently cleared")) }
        @if cleared.is_empty() {
            p.muted { (l.t("None.")) }
        } @else {
            (table(&cleared, &who, "/alarms", true))
        }
    };
    layout(l.t("Alarms"), who.viewer(), None, body).into_response()
}

#[derive(Deserialize)]
pub(super) struct AckForm {
    csrf: String,
    #[serde(default)]
    comment: String,
    #[serde(default)]
    back: String,
}

/// `POST /alarms/{id}/ack` from the acknowledge form; back to the page it came from.
pub(super) async fn acknowledge(
    State(app): State<Arc<AppState>>,
    who: SignedIn,
    Path(id): Path<String>,
    Form(form): Form<AckForm>,
) -> Response {
    let (session, l) = (&who.session, who.locale);
    if !session.csrf_matches(Some(&form.csrf)) {
        return problem(
            StatusCode::FORBIDDEN,
            who.viewer(),
            l.t("The form has expired; reload the page."),
        );
    }
    if !session.operator.may(Role::Technician) {
        return problem(
            StatusCode::FORBIDDEN,
            who.viewer(),
            l.t("A viewer cannot acknowledge alarms."),
        );
    }
    let comment: String = form.comment.chars().take(1000).collect();
    let done = match id.parse::<i64>() {
        Ok(id) => {
            app.alarms
                .acknowledge(
                    &session.operator.account.domain,
                    id,
                    &session.operator.user,
                    &comment,
                )
                .await
        }
        Err(_) => Err(AckError::NotFound),
    };
    match done {
        Ok(_) | Err(AckError::Already(_)) => {
            // Only a path of this site: never an open redirect.
            let back = Some(form.back.as_str())
                .filter(|b| b.starts_with('/') && !b.starts_with("//"))
                .unwrap_or("/alarms");
            Redirect::to(back).into_response()
        }
        Err(AckError::NotFound) => {
            problem(StatusCode::NOT_FOUND, who.viewer(), l.t("No such alarm."))
        }
        Err(AckError::Store(e)) => unavailable(e, who.viewer()),
    }
}
