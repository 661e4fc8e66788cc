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

use super::page::{layout, problem, time};
use super::session::Session;
use super::SignedIn;
use crate::alarms::service::AckError;
use crate::alarms::{Alarm, Severity};
use crate::api::App;
use crate::store::AlarmFilter;

/// A severity as a coloured badge.
pub(super) fn severity_badge(severity: Severity) -> Markup {
    html! { span.badge.{ "sev-" (severity.name()) } { (severity.name()) } }
}

/// An RFC 3339 time as a local time on the page.
fn at(text: &str) -> Markup {
    time(nxg::msg::parse_time(text).unwrap_or(0))
}

/// Where an alarm is, in words.
fn place(alarm: &Alarm) -> String {
    match alarm.node {
        Some(p) => match p.id {
            Some(id) => format!("node {id} (net {})", p.net),
            None => format!("net {}", p.net),
        },
        None => "gateway".into(),
    }
}

/// Alarms as a table; active ones not yet taken on have an acknowledge form that returns to
/// `back`.
pub(super) fn table(alarms: &[Alarm], session: &Session, back: &str, lifts: bool) -> Markup {
    html! {
        table.alarms {
            thead { tr {
                th { "Severity" } @if lifts { th { "Lift" } } th { "Where" } th { "Alarm" }
                th { "Raised" } th { "Acknowledged" } th { "Cleared" }
            } }
            tbody {
                @for a in alarms {
                    tr data-alarm=(a.id) {
                        td { (severity_badge(a.severity)) }
                        @if lifts { td { a href={ "/lifts/" (a.lift) } { (a.lift) } } }
                        td { (place(a)) }
                        td { (a.text) }
                        td { (at(&a.raised)) }
                        td {
                            @if let Some(ack) = &a.acknowledged {
                                (ack.by) ", " (at(&ack.at))
                                @if !ack.comment.is_empty() { br; span.muted { (ack.comment) } }
                            } @else {
                                form.ack method="post" action={ "/alarms/" (a.id) "/ack" } {
                                    input type="hidden" name="csrf" value=(session.csrf);
                                    input type="hidden" name="back" value=(back);
                                    input name="comment" placeholder="comment" maxlength="1000";
                                    button { "Acknowledge" }
                                }
                            }
                        }
                        td {
                            @if let Some(c) = &a.cleared { (at(c)) } @else { span.fault { "active" } }
                        }
                    }
                }
            }
        }
    }
}

/// A lift's bus events, newest first.
pub(super) fn event_log(events: &[Event]) -> Markup {
    html! {
        table.events {
            thead { tr { th { "Time" } th { "Type" } th { "Where" } th { "What" } } }
            tbody {
                @for e in events.iter().rev() {
                    @match e {
                        Event::Emcy { node, time: t, code, register, text, .. } => tr {
                            td { (at(t)) } td { "EMCY" }
                            td { "node " (node.id.get()) " (net " (node.net) ")" }
                            td { (text) " " span.muted { (code) ", register " (register) } }
                        },
                        Event::State { node, time: t, state } => tr {
                            td { (at(t)) } td { "state" }
                            td { "node " (node.id.get()) " (net " (node.net) ")" }
                            td { (state.name()) }
                        },
                        Event::Bus { net, time: t, state } => tr {
                            td { (at(t)) } td { "network" } td { "net " (net) }
                            td { (state.name()) }
                        },
                    }
                }
            }
        }
    }
}

pub(super) async fn alarms_page(
    State(app): State<Arc<App>>,
    SignedIn(session): SignedIn,
) -> Response {
    let domain = &session.account.domain;
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
        (Err(e), _) | (_, Err(e)) => return e.into(),
    };
    let cleared: Vec<Alarm> = recent.into_iter().filter(|a| !a.active()).collect();
    let body = html! {
        h1 { "Alarms" }
        @if active.is_empty() {
            p.ok { "No active alarm." }
        } @else {
            p.summary { (active.len()) " active" }
            (table(&active, &session, "/alarms", true))
        }
        h2 { "Recently cleared" }
        @if cleared.is_empty() {
            p.muted { "None." }
        } @else {
            (table(&cleared, &session, "/alarms", true))
        }
    };
    layout("Alarms", Some(&session), None, body).into_response()
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
    State(app): State<Arc<App>>,
    SignedIn(session): SignedIn,
    Path(id): Path<String>,
    Form(form): Form<AckForm>,
) -> Response {
    if !session.csrf_matches(Some(&form.csrf)) {
        return problem(
            StatusCode::FORBIDDEN,
            Some(&session),
            "The form has expired; reload the page.",
        );
    }
    let comment: String = form.comment.chars().take(1000).collect();
    let done = match id.parse::<i64>() {
        Ok(id) => {
            app.alarms
                .acknowledge(&session.account.domain, id, &session.account.name, &comment)
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
        Err(AckError::NotFound) => problem(StatusCode::NOT_FOUND, Some(&session), "No such alarm."),
        Err(AckError::Store(e)) => e.into(),
    }
}
