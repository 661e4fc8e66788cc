//! Signing in with an account's API key, and out.

use std::sync::Arc;

use axum::extract::{Form, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Redirect, Response};
use maud::html;
use serde::Deserialize;

use super::i18n::Locale;
use super::page::{layout, problem, unavailable, Viewer};
use super::session::{COOKIE, IDLE};
use crate::api::App;

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
                (l.t("API key "))
                input type="password" name="key" autocomplete="current-password" required autofocus;
            }
            button { (l.t("Sign in")) }
        }
        p.hint {
            (l.t("The key was printed once by ")) code { "canlift cloud account add" }
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
    key: String,
}

pub(super) async fn login(
    State(app): State<Arc<App>>,
    locale: Locale,
    Form(form): Form<LoginForm>,
) -> Response {
    match app.store.account_by_key(form.key.trim()).await {
        Ok(Some(account)) => {
            tracing::info!(account = %account.name, "web sign-in");
            let id = app.sessions.open(account);
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
        Ok(None) => (
            StatusCode::UNAUTHORIZED,
            login_form(Some(locale.t("Unknown API key.")), locale),
        )
            .into_response(),
        Err(e) => unavailable(
            e,
            Viewer {
                session: None,
                locale,
            },
        ),
    }
}

#[derive(Deserialize)]
pub(super) struct LogoutForm {
    csrf: String,
}

pub(super) async fn logout(
    State(app): State<Arc<App>>,
    locale: Locale,
    headers: HeaderMap,
    Form(form): Form<LogoutForm>,
) -> Response {
    if let Some(session) = app.sessions.get(&headers) {
        if !session.csrf_matches(Some(&form.csrf)) {
            let viewer = Viewer {
                session: Some(&session),
                locale,
            };
            return problem(StatusCode::FORBIDDEN, viewer, locale.t("Wrong CSRF token."));
        }
        app.sessions.close(&headers);
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
