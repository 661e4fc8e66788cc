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
use crate::auth::sessions::{Credential, COOKIE, IDLE};
use crate::state::AppState;

pub(super) async fn login_page(locale: Locale) -> Response {
    login_form(None, locale)
}

fn login_form(error: Option<&str>, l: Locale) -> Response {
    let body = html! {
        h1 { (l.t("Sign in")) }
        @if let Some(e) = error {
            p.error { (e) }
        }
        form.login method="post" action="/login" {
            label {
                (l.t("User name "))
                input type="text" name="user" autocomplete="username" autofocus;
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
    let viewer = Viewer {
        session: None,
        locale: l,
    };
    layout(l.t("Sign in"), viewer, None, body).into_response()
}

#[derive(Deserialize)]
pub(super) struct LoginForm {
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
    Form(form): Form<LoginForm>,
) -> Response {
    let epoch = app.store.seen_auth_epoch();
    let key = form.key.trim();
    // Failed attempts make the next ones wait, per name (keys count as one name) and address.
    let name = if key.is_empty() {
        form.user.trim()
    } else {
        "(API key)"
    };
    let address = peer.ip().to_string();
    let sign_ins = || {
        app.auth
            .sign_ins
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    };
    let waiting = sign_ins().check(name, &address, Instant::now());
    if let Err(wait) = waiting {
        tracing::warn!(user = name, %address, wait_s = wait.as_secs(), "sign-in throttled");
        let text = locale.fill(
            "Too many failed sign-ins: try again in {} s.",
            &[&wait.as_secs().max(1)],
        );
        let mut response = (
            StatusCode::TOO_MANY_REQUESTS,
            login_form(Some(&text), locale),
        )
            .into_response();
        response
            .headers_mut()
            .insert(header::RETRY_AFTER, crate::errors::retry_after(wait));
        return response;
    }
    let signed_in = if key.is_empty() {
        let user = form.user.trim();
        app.store
            .sign_in(user, form.secret.trim())
            .await
            .map(|o| o.map(|o| (o, Credential::User(user.to_owned()))))
    } else {
        app.store
            .operator_by_key(key)
            .await
            .map(|o| o.map(|o| (o, Credential::Key(cloud_store::digest(key)))))
    };
    match signed_in {
        Ok(Some((operator, credential))) => {
            sign_ins().succeeded(name, &address);
            tracing::info!(user = %operator.user, account = %operator.account.name, "web sign-in");
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
                response.headers_mut().insert(header::SET_COOKIE, v);
            }
            response
        }
        Ok(None) => {
            sign_ins().failed(name, &address, Instant::now());
            let text = locale.t("Wrong user name, secret or API key.");
            (StatusCode::UNAUTHORIZED, login_form(Some(text), locale)).into_response()
        }
        Err(e) => database_down(e, locale),
    }
}

/// The page for a sign-in or sign-out the database failed.
fn database_down(e: cloud_store::StoreError, locale: Locale) -> Response {
    let viewer = Viewer {
        session: None,
        locale,
    };
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
