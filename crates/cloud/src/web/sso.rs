//! Signing in through the account's OpenID provider (docs/PORTAL.md §Single sign-on):
//! `/login/sso` sends the browser to the provider with the flow's state in a cookie of its own,
//! `/login/sso/callback` takes the answer, checks it ([`crate::auth::oidc`]), makes or updates
//! the user with the role their groups give and opens a session as a sign-in with a secret does.

use std::sync::Arc;

use axum::extract::{Query, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Redirect, Response};
use serde::Deserialize;

use super::i18n::Locale;
use super::login::{database_down, login_form, open_session, sso_label};
use super::page::{problem, Viewer};
use crate::auth::oidc::{Pending, SignedOn, Sso, SsoError};
use crate::auth::sessions::{cookie, Credential};
use crate::state::AppState;
use cloud_store::UserError;

/// The cookie that keeps the flow's state while the browser is at the provider.
const COOKIE: &str = "canlift_sso";
/// How long a sign-on may take at the provider.
const PENDING_S: u64 = 600;

/// Where the provider sends the browser back: `[oidc] redirect_url`, else this portal as the
/// browser reached it.
fn redirect_url(sso: &Sso, headers: &HeaderMap) -> Option<String> {
    if let Some(url) = &sso.section.redirect_url {
        return Some(url.clone());
    }
    let host = headers.get(header::HOST)?.to_str().ok()?;
    // A Host header is the browser's word; a wrong one only sends the provider a redirect
    // address it has not registered, which it refuses.
    host.bytes()
        .all(|b| b.is_ascii_alphanumeric() || b".-:[]".contains(&b))
        .then(|| format!("https://{host}/login/sso/callback"))
}

/// The flow's cookie set to `value` for `max_age` seconds (0: gone). `SameSite=Lax`: the
/// browser comes back from the provider by a top-level navigation, which Lax lets it carry.
fn flow_cookie(value: &str, max_age: u64) -> Option<HeaderValue> {
    HeaderValue::from_str(&format!(
        "{COOKIE}={value}; Path=/login/sso; HttpOnly; Secure; SameSite=Lax; Max-Age={max_age}"
    ))
    .ok()
}

/// `GET /login/sso`: to the provider.
pub(super) async fn start(
    State(app): State<Arc<AppState>>,
    locale: Locale,
    headers: HeaderMap,
) -> Response {
    let Some(sso) = &app.auth.sso else {
        return problem(
            StatusCode::NOT_FOUND,
            Viewer::signed_out(locale),
            locale.t("Single sign-on is not set up on this portal."),
        );
    };
    let Some(redirect) = redirect_url(sso, &headers) else {
        return problem(
            StatusCode::BAD_REQUEST,
            Viewer::signed_out(locale),
            locale.t("Sign in from the portal's own page."),
        );
    };
    match sso.begin(&redirect).await {
        Ok((url, pending)) => {
            let mut response = Redirect::to(&url).into_response();
            if let Some(cookie) = flow_cookie(&pending.to_cookie(), PENDING_S) {
                response.headers_mut().insert(header::SET_COOKIE, cookie);
            }
            response
        }
        Err(e) => provider_down(&e, locale),
    }
}

fn provider_down(e: &SsoError, locale: Locale) -> Response {
    tracing::warn!(error = %e, "single sign-on: the provider is unavailable");
    problem(
        StatusCode::SERVICE_UNAVAILABLE,
        Viewer::signed_out(locale),
        locale.t("The sign-on provider cannot be reached: try again, or sign in with a secret or an API key."),
    )
}

/// The provider's answer (Core §3.1.2.5 and §3.1.2.6; `iss` of RFC 9207).
#[derive(Deserialize)]
pub(super) struct Answer {
    code: Option<String>,
    state: Option<String>,
    iss: Option<String>,
    error: Option<String>,
    error_description: Option<String>,
}

/// `GET /login/sso/callback`: back from the provider.
pub(super) async fn callback(
    State(app): State<Arc<AppState>>,
    locale: Locale,
    headers: HeaderMap,
    Query(answer): Query<Answer>,
) -> Response {
    let mut response = finish(&app, locale, &headers, answer).await;
    // The flow's state is spent whatever the outcome: an answer is taken once.
    if let Some(gone) = flow_cookie("", 0) {
        response.headers_mut().append(header::SET_COOKIE, gone);
    }
    response
}

async fn finish(app: &AppState, locale: Locale, headers: &HeaderMap, answer: Answer) -> Response {
    let Some(sso) = &app.auth.sso else {
        return problem(
            StatusCode::NOT_FOUND,
            Viewer::signed_out(locale),
            locale.t("Single sign-on is not set up on this portal."),
        );
    };
    let refuse = |status: StatusCode, text: &str| {
        (status, login_form(Some(text), sso_label(app), locale)).into_response()
    };
    let pending = cookie(headers, COOKIE).and_then(Pending::from_cookie);
    // The answer must be to this browser's own request (a forged one is not: login CSRF).
    let Some(pending) = pending.filter(|p| answer.state.as_deref() == Some(p.state.as_str()))
    else {
        return refuse(
            StatusCode::FORBIDDEN,
            locale.t("This sign-on was not begun in this browser, or took longer than ten minutes: sign in again."),
        );
    };
    // RFC 9207: an answer naming another issuer comes from another provider (a mix-up).
    if answer
        .iss
        .as_deref()
        .is_some_and(|iss| iss != sso.section.issuer)
    {
        tracing::warn!(iss = ?answer.iss, "single sign-on: an answer of another issuer");
        return refuse(
            StatusCode::FORBIDDEN,
            locale.t("The sign-on could not be verified."),
        );
    }
    if let Some(error) = &answer.error {
        let why = match &answer.error_description {
            Some(d) => format!("{error}: {d}"),
            None => error.clone(),
        };
        tracing::info!(%why, "single sign-on refused by the provider");
        let text = locale.fill("The sign-on provider refused: {}", &[&why]);
        return refuse(StatusCode::UNAUTHORIZED, &text);
    }
    let (Some(code), Some(redirect)) = (answer.code.as_deref(), redirect_url(sso, headers)) else {
        return refuse(
            StatusCode::BAD_REQUEST,
            locale.t("The sign-on could not be verified."),
        );
    };
    let epoch = app.store.seen_auth_epoch();
    let signed_on = match sso.finish(code, &pending, &redirect).await {
        Ok(s) => s,
        Err(SsoError::Token(why) | SsoError::UnknownKey(why)) => {
            tracing::warn!(%why, "single sign-on: the ID token was refused");
            return refuse(
                StatusCode::FORBIDDEN,
                locale.t("The sign-on could not be verified."),
            );
        }
        Err(SsoError::Refused(why)) => {
            tracing::info!(%why, "single sign-on refused by the provider");
            let text = locale.fill("The sign-on provider refused: {}", &[&why]);
            return refuse(StatusCode::UNAUTHORIZED, &text);
        }
        Err(e) => return provider_down(&e, locale),
    };
    let SignedOn {
        subject,
        name,
        role,
    } = signed_on;
    let account = &sso.section.account;
    let Some(role) = role else {
        tracing::warn!(user = %name, %account, "single sign-on refused: no group of theirs gives a role");
        return refuse(
            StatusCode::FORBIDDEN,
            locale.t("None of your groups gives a role on this portal: ask its administrator."),
        );
    };
    match app
        .store
        .signed_on_user(account, &subject, &name, role)
        .await
    {
        Ok(Some(operator)) => {
            tracing::info!(user = %operator.user, %account, role = role.name(), "web sign-in by single sign-on");
            let credential = Credential::User {
                account: account.clone(),
                name: operator.user.clone(),
            };
            open_session(app, operator, credential, epoch, locale).await
        }
        Ok(None) => refuse(
            StatusCode::FORBIDDEN,
            locale.t("Your user is disabled on this portal: ask its administrator."),
        ),
        Err(UserError::Taken(name)) => {
            tracing::warn!(user = %name, %account, "single sign-on refused: a user of the portal has the name");
            let text = locale.fill(
                "The portal has another user named {}: its administrator must rename or remove it.",
                &[&name],
            );
            refuse(StatusCode::CONFLICT, &text)
        }
        Err(UserError::Store(e)) => database_down(e, locale),
        Err(e) => {
            tracing::error!(error = %e, "single sign-on: [oidc] account");
            problem(
                StatusCode::INTERNAL_SERVER_ERROR,
                Viewer::signed_out(locale),
                locale.t("Single sign-on is not set up on this portal."),
            )
        }
    }
}
