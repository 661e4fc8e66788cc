//! Signing in with a user's name and secret (or an API key), and out. A wrong secret and an
//! unknown name get the same answer after the same work (docs/PORTAL.md §Users and roles).

use std::net::SocketAddr;
use std::sync::{Arc, PoisonError};
use std::time::Instant;

use axum::extract::{ConnectInfo, Form, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Redirect, Response};
use maud::html;
use serde::Deserialize;

use super::i18n::Locale;
use super::page::{layout, problem, unavailable, Viewer};
use crate::auth::passwords::Busy;
use crate::auth::sessions::{Credential, COOKIE, IDLE};
use crate::state::AppState;
use crate::throttle::Attempt;

pub(super) async fn login_page(State(app): State<Arc<AppState>>, locale: Locale) -> Response {
    login_form(None, sso_label(&app), locale)
}

/// The button's label of single sign-on, when the portal has it.
pub(super) fn sso_label(app: &AppState) -> Option<&str> {
    app.auth.sso.as_ref().map(|sso| sso.section.label.as_str())
}

/// The sign-in page, with `error` above the form and the single sign-on button if `sso`.
pub(super) fn login_form(error: Option<&str>, sso: Option<&str>, l: Locale) -> Response {
    let body = html! {
        h1 { (l.t("Sign in")) }
        @if let Some(e) = error {
            p.error { (e) }
        }
        @if let Some(label) = sso {
            // A link, not a form: the provider is another origin, which the page's
            // form-action does not allow.
            p.sso { a.button href="/login/sso" { (l.fill("Sign in with {}", &[&label])) } }
            p.or { (l.t("or with the portal's own sign-in")) }
        }
        form.login method="post" action="/login" {
            label {
                (l.t("Account "))
                input type="text" name="account" autocomplete="organization" autofocus;
            }
            label {
                (l.t("User name "))
                input type="text" name="user" autocomplete="username";
            }
            label {
                (l.t("Secret "))
                input type="password" name="secret" autocomplete="current-password";
            }
            p.or { (l.t("or with an API key")) }
            label {
                (l.t("API key "))
                input type="password" name="key" autocomplete="off";
            }
            button { (l.t("Sign in")) }
        }
        p.hint {
            (l.t("A user's secret is printed once by ")) code { "canlift cloud user add" }
            (l.t("; an account's key by ")) code { "canlift cloud account add" }
            (l.t(" (or by ")) code { "canlift demo" } (l.t(")."))
        }
    };
    let viewer = Viewer::signed_out(l);
    layout(l.t("Sign in"), viewer, None, body).into_response()
}

#[derive(Deserialize)]
pub(super) struct LoginForm {
    #[serde(default)]
    account: String,
    #[serde(default)]
    user: String,
    #[serde(default)]
    secret: String,
    #[serde(default)]
    key: String,
}

pub(super) async fn login(
    State(app): State<Arc<AppState>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    locale: Locale,
    headers: HeaderMap,
    Form(form): Form<LoginForm>,
) -> Response {
    // Login CSRF: another site's form must not sign the browser in to an account of the
    // attacker's choosing (where a victim would type a lift's password into a rogue lift).
    if !same_origin(&headers) {
        let viewer = Viewer::signed_out(locale);
        return problem(
            StatusCode::FORBIDDEN,
            viewer,
            locale.t("Sign in from the portal's own page."),
        );
    }
    let epoch = app.store.seen_auth_epoch();
    let key = form.key.trim();
    let (account, user) = (form.account.trim(), form.user.trim());
    // One name per account and user: the throttle's and the log's.
    let qualified = format!("{user}@{account}");
    let attempt = if key.is_empty() {
        Attempt::User(&qualified)
    } else {
        Attempt::Key
    };
    let address = peer.to_string();
    let sign_ins = || {
        app.auth
            .sign_ins
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    };
    if let Err(wait) = sign_ins().begin(attempt, &address, Instant::now()) {
        tracing::warn!(user = %qualified, %address, wait_s = wait.as_secs(), "sign-in throttled");
        let text = locale.fill(
            "Too many failed sign-ins: try again in {} s.",
            &[&wait.as_secs().max(1)],
        );
        return too_many(&text, wait, locale);
    }
    let signed_in = if key.is_empty() {
        user_signs_in(&app, account, user, form.secret.trim())
            .await
            .map(|o| {
                o.map(|o| {
                    let credential = Credential::User {
                        account: account.to_owned(),
                        name: user.to_owned(),
                    };
                    (o, credential)
                })
            })
    } else {
        app.store
            .operator_by_key(key)
            .await
            .map(|o| o.map(|o| (o, Credential::Key(cloud_store::digest(key)))))
            .map_err(Undecided::Store)
    };
    match signed_in {
        Ok(Some((operator, credential))) => {
            sign_ins().succeeded(attempt, &address);
            tracing::info!(user = %operator.user, account = %operator.account.name, "web sign-in");
            open_session(&app, operator, credential, epoch, locale).await
        }
        Ok(None) => {
            let text = locale.t("Wrong account, user name, secret or API key.");
            let sso = sso_label(&app);
            (
                StatusCode::UNAUTHORIZED,
                login_form(Some(text), sso, locale),
            )
                .into_response()
        }
        Err(Undecided::Busy(busy)) => {
            sign_ins().undecided(attempt, &address);
            too_many(&busy.to_string(), std::time::Duration::from_secs(1), locale)
        }
        Err(Undecided::Store(e)) => {
            sign_ins().undecided(attempt, &address);
            database_down(e, locale)
        }
    }
}

/// Whether a form post comes from the portal's own pages: its `Origin` (or, without one, its
/// `Referer`) is this host's HTTPS origin. A request with neither — not a browser's — is
/// taken as it is: CSRF needs a browser, and every browser sends `Origin` with a POST.
fn same_origin(headers: &HeaderMap) -> bool {
    let header = |name| {
        headers
            .get(name)
            .and_then(|v: &HeaderValue| v.to_str().ok())
    };
    let Some(host) = header(header::HOST) else {
        return false;
    };
    let ours = format!("https://{host}");
    match (header(header::ORIGIN), header(header::REFERER)) {
        (Some(origin), _) => origin == ours,
        (None, Some(referer)) => {
            referer == ours
                || referer
                    .strip_prefix(ours.as_str())
                    .is_some_and(|rest| rest.starts_with('/'))
        }
        (None, None) => true,
    }
}

/// Why a sign-in was neither let in nor refused.
enum Undecided {
    /// Too many secrets are being checked.
    Busy(Busy),
    /// The database did not answer.
    Store(cloud_store::StoreError),
}

/// User `user` of `account` with `secret`, if the secret is right and the user enabled: the
/// secret checked on the password threads, the same work for a name that does not exist.
async fn user_signs_in(
    app: &AppState,
    account: &str,
    user: &str,
    secret: &str,
) -> Result<Option<cloud_types::users::Operator>, Undecided> {
    let hash = app
        .store
        .secret_hash(account, user)
        .await
        .map_err(Undecided::Store)?;
    if !app
        .auth
        .passwords
        .check(secret, hash)
        .await
        .map_err(Undecided::Busy)?
    {
        return Ok(None);
    }
    app.store
        .operator(account, user)
        .await
        .map_err(Undecided::Store)
}

/// Open a session for `operator` signed in with `credential` (in auth epoch `epoch`): the
/// cookie, and on to the fleet.
pub(super) async fn open_session(
    app: &AppState,
    operator: cloud_types::users::Operator,
    credential: Credential,
    epoch: i64,
    locale: Locale,
) -> Response {
    let id = match app
        .auth
        .sessions
        .open(operator, credential, epoch, &app.store)
        .await
    {
        Ok(id) => id,
        Err(e) => return database_down(e, locale),
    };
    let cookie = format!(
        "{COOKIE}={id}; Path=/; HttpOnly; Secure; SameSite=Strict; Max-Age={}",
        IDLE.as_secs()
    );
    let mut response = Redirect::to("/").into_response();
    if let Ok(v) = HeaderValue::from_str(&cookie) {
        response.headers_mut().append(header::SET_COOKIE, v);
    }
    response
}

/// The sign-in page again, 429 with `Retry-After`.
fn too_many(text: &str, wait: std::time::Duration, locale: Locale) -> Response {
    let mut response = (
        StatusCode::TOO_MANY_REQUESTS,
        login_form(Some(text), None, locale),
    )
        .into_response();
    response
        .headers_mut()
        .insert(header::RETRY_AFTER, crate::errors::retry_after(wait));
    response
}

/// The page for a sign-in or sign-out the database failed.
pub(super) fn database_down(e: cloud_store::StoreError, locale: Locale) -> Response {
    let viewer = Viewer::signed_out(locale);
    unavailable(e, viewer)
}

#[derive(Deserialize)]
pub(super) struct LogoutForm {
    csrf: String,
}

pub(super) async fn logout(
    State(app): State<Arc<AppState>>,
    locale: Locale,
    headers: HeaderMap,
    Form(form): Form<LogoutForm>,
) -> Response {
    let session = match app.auth.sessions.get(&headers, &app.store).await {
        Ok(session) => session,
        Err(e) => return database_down(e, locale),
    };
    if let Some(session) = session {
        if !session.csrf_matches(Some(&form.csrf)) {
            let viewer = Viewer {
                session: Some(&session),
                locale,
            };
            return problem(StatusCode::FORBIDDEN, viewer, locale.t("Wrong CSRF token."));
        }
        if let Err(e) = app.auth.sessions.close(&headers, &app.store).await {
            return database_down(e, locale);
        }
    }
    let mut response = Redirect::to("/login").into_response();
    response.headers_mut().insert(
        header::SET_COOKIE,
        HeaderValue::from_static(
            "canlift_session=; Path=/; HttpOnly; Secure; SameSite=Strict; Max-Age=0",
        ),
    );
    response
}
