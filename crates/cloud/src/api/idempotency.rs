//! `Idempotency-Key` on the API's writes (`PUT` and `POST`; the IETF httpapi draft's header,
//! docs/PORTAL.md §Idempotency): an operator who retries a write after a lost answer or a
//! timeout, with the same key, gets the first attempt's answer instead of a second write. Keys
//! belong to the credential that sent them (an API key, or a browser session) and are kept for
//! a day. A key still in progress answers 409, a key reused for another request 422; a first
//! attempt that was refused before anything happened (429, 503) leaves its key free.

use std::sync::Arc;

use axum::body::{Body, Bytes};
use axum::extract::{Request, State};
use axum::http::{header, HeaderMap, HeaderValue, Method, StatusCode};
use axum::middleware::Next;
use axum::response::{IntoResponse, Response};
use cloud_store::Idempotent;
use http_body_util::BodyExt;

use crate::errors::error;
use crate::state::AppState;

/// The header.
const HEADER: &str = "idempotency-key";

/// Longest body of a request or an answer held to fingerprint or record it.
const MAX_BODY: usize = 1 << 20;

/// The key of `headers`, if any: a Structured Fields string (`"…"`) or a bare token, 1 to 255
/// visible ASCII characters; `Err` with why for one that is malformed.
fn key_of(headers: &HeaderMap) -> Result<Option<String>, &'static str> {
    let Some(value) = headers.get(HEADER) else {
        return Ok(None);
    };
    let text = value.to_str().map_err(|_| "not ASCII")?.trim();
    let text = text
        .strip_prefix('"')
        .and_then(|t| t.strip_suffix('"'))
        .unwrap_or(text);
    if text.is_empty() || text.len() > 255 || !text.bytes().all(|b| b.is_ascii_graphic()) {
        return Err("1 to 255 visible ASCII characters");
    }
    Ok(Some(text.to_owned()))
}

/// Whose key it is: a digest of the request's credential (the bearer key or the session
/// cookie), so that one operator's keys are never another's.
fn scope_of(headers: &HeaderMap) -> Option<String> {
    let credential = headers
        .get(header::AUTHORIZATION)
        .or_else(|| headers.get(header::COOKIE))?;
    Some(cloud_store::digest(&String::from_utf8_lossy(
        credential.as_bytes(),
    )))
}

/// Carry out a `PUT` or `POST` with an `Idempotency-Key` once.
pub async fn once(State(app): State<Arc<AppState>>, request: Request, next: Next) -> Response {
    if !matches!(*request.method(), Method::PUT | Method::POST) {
        return next.run(request).await;
    }
    let key = match key_of(request.headers()) {
        Ok(Some(key)) => key,
        Ok(None) => return next.run(request).await,
        Err(why) => {
            return error(StatusCode::BAD_REQUEST, format!("Idempotency-Key: {why}"))
                .into_response()
        }
    };
    // Without a credential the request is refused anyway (401): nothing to remember.
    let Some(scope) = scope_of(request.headers()) else {
        return next.run(request).await;
    };
    let (parts, body) = request.into_parts();
    let Ok(body) = collect(body).await else {
        return error(StatusCode::PAYLOAD_TOO_LARGE, "request body too large").into_response();
    };
    let target = parts.uri.path_and_query().map_or("", |p| p.as_str());
    let fingerprint = cloud_store::digest(&format!(
        "{} {target}\n{}",
        parts.method,
        String::from_utf8_lossy(&body)
    ));
    let now = cloud_types::now_ms();
    match app
        .store
        .idempotency_begin(&scope, &key, &fingerprint, now)
        .await
    {
        Err(e) => {
            tracing::warn!(error = %e, "Idempotency-Key not honoured: database");
            error(
                StatusCode::SERVICE_UNAVAILABLE,
                "database unavailable: a write with an Idempotency-Key cannot be carried out once",
            )
            .into_response()
        }
        Ok(Idempotent::Done { status, body }) => {
            let status = StatusCode::from_u16(status).unwrap_or(StatusCode::OK);
            let mut response = (status, body).into_response();
            let h = response.headers_mut();
            h.insert(
                header::CONTENT_TYPE,
                HeaderValue::from_static("application/json"),
            );
            h.insert("idempotency-replayed", HeaderValue::from_static("true"));
            response
        }
        Ok(Idempotent::InProgress) => error(
            StatusCode::CONFLICT,
            "a request with this Idempotency-Key is still in progress",
        )
        .into_response(),
        Ok(Idempotent::Mismatch) => error(
            StatusCode::UNPROCESSABLE_ENTITY,
            "this Idempotency-Key was used for another request",
        )
        .into_response(),
        Ok(Idempotent::New) => {
            let request = Request::from_parts(parts, Body::from(body));
            let response = next.run(request).await;
            let status = response.status();
            let (parts, body) = response.into_parts();
            let Ok(body) = collect(body).await else {
                let _ = app.store.idempotency_forget(&scope, &key).await;
                return error(StatusCode::INTERNAL_SERVER_ERROR, "answer too large")
                    .into_response();
            };
            let recorded = if matches!(
                status,
                StatusCode::TOO_MANY_REQUESTS | StatusCode::SERVICE_UNAVAILABLE
            ) {
                // Refused before anything happened: the key may be used again.
                app.store.idempotency_forget(&scope, &key).await
            } else {
                let text = String::from_utf8_lossy(&body);
                app.store
                    .idempotency_finish(&scope, &key, status.as_u16(), &text)
                    .await
            };
            if let Err(e) = recorded {
                tracing::warn!(error = %e, "the outcome of an Idempotency-Key not recorded");
            }
            Response::from_parts(parts, Body::from(body))
        }
    }
}

/// A body up to [`MAX_BODY`] bytes.
async fn collect(body: Body) -> Result<Bytes, ()> {
    let limited = http_body_util::Limited::new(body, MAX_BODY);
    limited
        .collect()
        .await
        .map(|c| c.to_bytes())
        .map_err(|_| ())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_strings_or_tokens_of_visible_ascii() {
        let headers = |v: &str| {
            let mut h = HeaderMap::new();
            h.insert(HEADER, HeaderValue::from_str(v).unwrap());
            h
        };
        assert_eq!(key_of(&HeaderMap::new()), Ok(None));
        assert_eq!(
            key_of(&headers("\"8e03978e-40d5-43e8-bc93-6894a57f9324\"")),
            Ok(Some("8e03978e-40d5-43e8-bc93-6894a57f9324".into()))
        );
        assert_eq!(key_of(&headers("retry-1")), Ok(Some("retry-1".into())));
        assert!(key_of(&headers("\"\"")).is_err());
        assert!(key_of(&headers("a b")).is_err());
        assert!(key_of(&headers(&"k".repeat(256))).is_err());
    }
}
