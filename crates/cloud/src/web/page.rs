//! What every page shares: the layout with navigation, error pages, times, the online badge.
//! Pages are maud templates: text is escaped unless a template says otherwise.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use maud::{html, Markup, PreEscaped, DOCTYPE};

use super::assets;
use super::i18n::Locale;
use crate::auth::sessions::Session;
use cloud_types::users::Role;

use cloud_store::StoreError;

/// Characters a path segment carries as they are (RFC 3986 unreserved); all else is
/// percent-encoded.
const SEGMENT: &percent_encoding::AsciiSet = &percent_encoding::NON_ALPHANUMERIC
    .remove(b'-')
    .remove(b'.')
    .remove(b'_')
    .remove(b'~');

/// The path of the page of lift `key` (a registry key or the id its account sees): the id,
/// percent-encoded — a serial number may hold `/`, `?`, `#` or spaces.
pub(super) fn lift_path(key: &str) -> String {
    let id = cloud_types::lifts::shown_id(key);
    format!(
        "/lifts/{}",
        percent_encoding::utf8_percent_encode(id, SEGMENT)
    )
}

/// What every page is rendered for: the signed-in browser (absent: the sign-in page, without
/// navigation) and its language.
#[derive(Clone, Copy)]
pub(super) struct Viewer<'a> {
    pub session: Option<&'a Session>,
    pub locale: Locale,
}

impl Viewer<'static> {
    /// A browser nobody is signed in with (the sign-in pages, their refusals).
    pub(super) fn signed_out(locale: Locale) -> Viewer<'static> {
        Viewer {
            session: None,
            locale,
        }
    }
}

/// A whole page. `lift`: the lift whose live events the page's script follows.
pub(super) fn layout(title: &str, viewer: Viewer, lift: Option<&str>, body: Markup) -> Markup {
    let l = viewer.locale;
    html! {
        (DOCTYPE)
        html lang=(l.code()) {
            head {
                meta charset="utf-8";
                meta name="viewport" content="width=device-width, initial-scale=1";
                @if let Some(s) = viewer.session {
                    meta name="csrf" content=(s.csrf);
                }
                title { (title) " · canlift" }
                link rel="stylesheet" href=(assets::url("style.css"));
                link rel="icon" href=(assets::url("favicon.svg")) type="image/svg+xml";
                script type="application/json" #texts { (PreEscaped(l.script_texts())) }
                script src=(assets::url("app.js")) defer {}
            }
            body data-lift=[lift] {
                header {
                    a.brand href="/" { "canlift" }
                    nav {
                        @if let Some(s) = viewer.session {
                            a href="/" { (l.t("Fleet")) }
                            a href="/alarms" { (l.t("Alarms")) }
                            a href="/audit" { (l.t("Audit")) }
                            a href="/reports" { (l.t("Reports")) }
                            span.who title=(role_text(s.operator.role, l)) {
                                (s.operator.user) " · " (role_text(s.operator.role, l))
                            }
                            form method="post" action="/logout" {
                                input type="hidden" name="csrf" value=(s.csrf);
                                button { (l.t("Sign out")) }
                            }
                        }
                        span.languages aria-label=(l.t("Language")) {
                            @for other in Locale::ALL {
                                a.current[other == l] href={ "?lang=" (other.code()) } lang=(other.code()) {
                                    (other.name())
                                }
                            }
                        }
                    }
                }
                main { (body) }
            }
        }
    }
}

/// A page that says what went wrong (`message` in the viewer's language).
pub(super) fn problem(status: StatusCode, viewer: Viewer, message: &str) -> Response {
    let body = html! {
        h1 { (status.as_u16()) }
        p.error { (message) }
    };
    (status, layout(status.as_str(), viewer, None, body)).into_response()
}

/// The page for a database failure.
pub(super) fn unavailable(e: StoreError, viewer: Viewer) -> Response {
    tracing::error!(error = %e, "web page failed on the database");
    let message = viewer.locale.t("The database is unavailable.");
    problem(StatusCode::INTERNAL_SERVER_ERROR, viewer, message)
}

/// Milliseconds since the epoch as `YYYY-MM-DD HH:MM:SS UTC` (the script shows local time).
pub(super) fn utc(ms: i64) -> String {
    let Ok(t) = time::OffsetDateTime::from_unix_timestamp(ms.div_euclid(1000)) else {
        return format!("{ms} ms");
    };
    format!(
        "{:04}-{:02}-{:02} {:02}:{:02}:{:02} UTC",
        t.year(),
        u8::from(t.month()),
        t.day(),
        t.hour(),
        t.minute(),
        t.second()
    )
}

/// A time the script shows in local time; "never" for none.
pub(super) fn time(ms: i64, l: Locale) -> Markup {
    html! {
        @if ms <= 0 {
            (l.t("never"))
        } @else {
            time data-ms=(ms) { (utc(ms)) }
        }
    }
}

/// The lift's online state, kept current by the script.
pub(super) fn online_badge(lift: &str, online: bool, l: Locale) -> Markup {
    let class = if online { "online" } else { "offline" };
    html! {
        span.badge.(class) data-online=(lift) { (l.t(class)) }
    }
}

/// A role in the page's language.
pub(super) fn role_text(role: Role, l: Locale) -> &'static str {
    match role {
        Role::Viewer => l.t("viewer"),
        Role::Technician => l.t("technician"),
        Role::Engineer => l.t("engineer"),
        Role::Admin => l.t("administrator"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escapes_markup() {
        let page = html! { p title=("\"x\"") { ("<a href=\"x\">'&'</a>") } }.into_string();
        assert_eq!(
            page,
            "<p title=\"&quot;x&quot;\">&lt;a href=&quot;x&quot;&gt;'&amp;'&lt;/a&gt;</p>"
        );
    }

    #[test]
    fn utc_dates() {
        assert_eq!(utc(0), "1970-01-01 00:00:00 UTC");
        assert_eq!(utc(951_782_400_000), "2000-02-29 00:00:00 UTC");
        assert_eq!(
            utc(1_795_392_000_000 + 3_723_000),
            "2026-11-23 01:02:03 UTC"
        );
    }
}
