//! The web UI: pages rendered on the server (maud templates: text is escaped unless a template
//! says otherwise), one small script (`web/app.js`) for live values, local times and the edit
//! dialog, one style sheet, no build step. One file per page; [`crate::auth::sessions`] keeps the
//! signed-in browsers. Every response carries a Content-Security-Policy that allows only this origin's
//! script and style.

mod alarms;
mod assets;
mod audit;
mod fleet;
mod history;
mod i18n;
mod lift;
mod login;
mod page;
mod reports;
mod sso;

use std::sync::Arc;

use axum::extract::FromRequestParts;
use axum::http::request::Parts;
use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{Redirect, Response};
use axum::routing::{get, post};
use axum::Router;

use crate::auth::sessions::Session;
use crate::state::AppState;
use cloud_types::lifts::LiftRecord;
use i18n::Locale;
use page::Viewer;

/// A page's signed-in browser and its language; without a session, the page redirects to the
/// sign-in form.
struct SignedIn {
    session: Session,
    locale: Locale,
}

impl SignedIn {
    fn viewer(&self) -> Viewer<'_> {
        Viewer {
            session: Some(&self.session),
            locale: self.locale,
        }
    }
}

impl FromRequestParts<Arc<AppState>> for SignedIn {
    type Rejection = Redirect;

    async fn from_request_parts(parts: &mut Parts, app: &Arc<AppState>) -> Result<Self, Redirect> {
        let Ok(locale) = Locale::from_request_parts(parts, app).await;
        match app.auth.sessions.current(&parts.headers, &app.store).await {
            Ok(Some(session)) => Ok(SignedIn { session, locale }),
            // Rights changed and could not be checked again: sign in anew.
            Ok(None) | Err(_) => Err(Redirect::to("/login")),
        }
    }
}

/// The lift, if it is one of the signed-in account's (a 404 page otherwise).
async fn owned(app: &AppState, who: &SignedIn, id: &str) -> Result<LiftRecord, Response> {
    match app.store.lift(&who.session.operator.account, id).await {
        Ok(Some(l)) => Ok(l),
        Ok(None) => Err(page::problem(
            StatusCode::NOT_FOUND,
            who.viewer(),
            who.locale.t("No such lift."),
        )),
        Err(e) => Err(page::unavailable(e, who.viewer())),
    }
}

/// Headers every UI response carries: only this origin's script and style, no framing, no
/// sniffing, no referrer to other sites.
async fn harden(mut response: Response) -> Response {
    let h = response.headers_mut();
    h.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(
            "default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' data:; \
             connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'self'",
        ),
    );
    h.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    // No referrer to other sites; to this one the page's origin, so that the sign-in form's
    // `Origin` is the portal's (with `no-referrer` browsers send `Origin: null`, which the
    // login-CSRF check must refuse).
    h.insert(
        header::REFERRER_POLICY,
        HeaderValue::from_static("same-origin"),
    );
    h.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
    response
}

/// The UI's routes.
pub fn routes(app: Arc<AppState>) -> Router {
    Router::new()
        .route("/", get(fleet::fleet))
        .route("/login", get(login::login_page).post(login::login))
        .route("/login/sso", get(sso::start))
        .route("/login/sso/callback", get(sso::callback))
        .route("/logout", post(login::logout))
        .route("/lifts/{id}", get(lift::lift_page))
        .route("/lifts/{id}/history", get(history::history_page))
        .route("/lifts/{id}/history.csv", get(history::history_csv))
        .route("/audit", get(audit::audit_page))
        .route("/reports", get(reports::reports_page))
        .route("/alarms", get(alarms::alarms_page))
        .route("/alarms/{id}/ack", post(alarms::acknowledge))
        .route("/static/{file}", get(assets::serve))
        .route("/favicon.ico", get(assets::favicon))
        .layer(axum::middleware::from_fn(i18n::remember))
        .layer(axum::middleware::map_response(harden))
        .with_state(app)
}
