//! The audit page: every change and privilege elevation on the account's lifts.

use std::sync::Arc;

use axum::extract::State;
use axum::response::{IntoResponse, Response};
use maud::html;

use super::page::{layout, time};
use super::SignedIn;
use crate::api::App;

/// An audit result as people read it: `error 134217761` is stored (the gateway's code), the
/// page says `08000021h: Access denied …`; JSON-RPC's negative codes get their meaning.
fn result_text(result: &str) -> String {
    use nxg::errors::{rpc_codes, ErrorCode};
    let Some(code) = result
        .strip_prefix("error ")
        .and_then(|c| c.parse::<i64>().ok())
    else {
        return result.to_owned();
    };
    match u32::try_from(code) {
        Ok(code) => format!("{code:08X}h: {}", ErrorCode(code).message("en")),
        Err(_) => rpc_codes::describe(code).map_or_else(|| "protocol error".into(), str::to_owned),
    }
}

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
                        td class=(if e.result == "ok" { "ok" } else { "fault" }) {
                            (result_text(&e.result))
                        }
                    }
                }
            }
        }
    };
    layout("Audit", Some(&session), None, body).into_response()
}

#[cfg(test)]
mod tests {
    use super::result_text;

    #[test]
    fn results_in_words() {
        assert_eq!(result_text("ok"), "ok");
        let refused = result_text("error 134217761");
        assert!(refused.starts_with("08000021h: "), "{refused}");
        assert_eq!(result_text("error -32602"), "invalid parameters");
        assert_eq!(result_text("error -1"), "protocol error");
        assert_eq!(result_text("timeout"), "timeout");
    }
}
