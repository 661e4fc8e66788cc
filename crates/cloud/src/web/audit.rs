//! The audit page: every change and privilege elevation on the account's lifts.

use std::sync::Arc;

use axum::extract::State;
use axum::response::{IntoResponse, Response};
use maud::html;

use super::page::{layout, time};
use super::SignedIn;
use crate::api::App;

pub(super) async fn audit_page(
    State(app): State<Arc<App>>,
    SignedIn(session): SignedIn,
) -> Response {
    let entries = match app.store.audit_log(&session.account.domain).await {
        Ok(e) => e,
        Err(e) => return e.into(),
    };
    let body = html! {
        h1 { "Audit" }
        p.summary { "Every change and privilege elevation, newest first." }
        table.audit {
            thead { tr {
                th { "When" } th { "Who" } th { "Lift" } th { "Action" } th { "Object" }
                th { "Before" } th { "After" } th { "Result" }
            } }
            tbody {
                @for e in &entries {
                    tr {
                        td { (time(e.at)) }
                        td { (e.account) }
                        td { a href={ "/lifts/" (e.lift) } { (e.lift) } }
                        td { (e.action) }
                        td { code { (e.object) } }
                        td { (e.old_value.as_deref().unwrap_or("")) }
                        td { (e.new_value) }
                        td class=(if e.result == "ok" { "ok" } else { "fault" }) { (e.result) }
                    }
                }
            }
        }
    };
    layout("Audit", Some(&session), None, body).into_response()
}
