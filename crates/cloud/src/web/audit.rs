//! The audit page: every change and privilege elevation on the account's lifts.

use std::sync::Arc;

use axum::extract::State;
use axum::response::{IntoResponse, Response};
use maud::html;

use super::i18n::Locale;
use super::page::{layout, lift_path, time, unavailable};
use super::SignedIn;
use crate::state::AppState;

/// An audit result as people read it: `error 134217761` is stored (the gateway's code), the
/// page says `08000021h: Access denied …`; JSON-RPC's negative codes get their meaning.
fn result_text(result: &str, l: Locale) -> String {
    use nxg::codes::{rpc_codes, ErrorCode};
    let Some(code) = result
        .strip_prefix("error ")
        .and_then(|c| c.parse::<i64>().ok())
    else {
        return if result == "ok" {
            l.t("ok").to_owned()
        } else {
            result.to_owned()
        };
    };
    match u32::try_from(code) {
        Ok(code) => format!("{code:08X}h: {}", ErrorCode(code).message(l.code())),
        Err(_) => {
            rpc_codes::describe(code).map_or_else(|| l.t("protocol error").into(), str::to_owned)
        }
    }
}

pub(super) async fn audit_page(State(app): State<Arc<AppState>>, who: SignedIn) -> Response {
    let l = who.locale;
    let entries = match app
        .store
        .audit_log(&who.session.operator.account.domain)
        .await
    {
        Ok(e) => e,
        Err(e) => return unavailable(e, who.viewer()),
    };
    let body = html! {
        h1 { (l.t("Audit")) }
        p.summary { (l.t("Every change and privilege elevation, newest first.")) }
        table.audit {
            thead { tr {
                th { (l.t("When")) } th { (l.t("Who")) } th { (l.t("Lift")) } th { (l.t("Action")) }
                th { (l.t("Object")) } th { (l.t("Before")) } th { (l.t("After")) }
                th { (l.t("Result")) }
            } }
            tbody {
                @for e in &entries {
                    tr {
                        td { (time(e.at, l)) }
                        td { (e.account) }
                        td { a href=(lift_path(&e.lift)) { (e.lift) } }
                        td { (e.action) }
                        td { code { (e.object) } }
                        td { (e.old_value.as_deref().unwrap_or("")) }
                        td { (e.new_value) }
                        td class=(if e.result == "ok" { "ok" } else { "fault" }) {
                            (result_text(&e.result, l))
                        }
                    }
                }
            }
        }
    };
    layout(l.t("Audit"), who.viewer(), None, body).into_response()
}

#[cfg(test)]
mod tests {
    use super::{result_text, Locale};

    #[test]
    fn results_in_words() {
        let en = |r| result_text(r, Locale::En);
        assert_eq!(en("ok"), "ok");
        let refused = en("error 134217761");
        assert!(refused.starts_with("08000021h: "), "{refused}");
        assert_eq!(en("error -32602"), "invalid parameters");
        assert_eq!(en("error -1"), "protocol error");
        assert_eq!(en("timeout"), "timeout");
        assert_eq!(result_text("error -1", Locale::De), "Protokollfehler");
    }
}
