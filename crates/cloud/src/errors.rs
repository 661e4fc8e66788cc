//! The portal's error answers over HTTP: a status and the connector's error object
//! ([`nxg::msg::ErrorObject`]), with `Retry-After` where waiting helps; how database and
//! gateway failures map to them; and the extractors that answer malformed queries and bodies
//! the same way.

use axum::extract::rejection::{JsonRejection, QueryRejection};
use axum::extract::{FromRequest, FromRequestParts, Request};
use axum::http::request::Parts;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::Json;
use nxg::codes::ErrorCode;
use nxg::msg::ErrorObject;
use nxg::portal::Failure;
use serde::de::DeserializeOwned;

/// An error answer: the status and an error object (and, for 429, when to try again).
pub struct ApiError(
    pub StatusCode,
    pub ErrorObject,
    pub Option<std::time::Duration>,
);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut response = (self.0, Json(self.1)).into_response();
        if let Some(wait) = self.2 {
            response
                .headers_mut()
                .insert(axum::http::header::RETRY_AFTER, retry_after(wait));
        }
        response
    }
}

/// `Retry-After` in whole seconds, rounded up (RFC 9110 §10.2.3).
pub fn retry_after(wait: std::time::Duration) -> axum::http::HeaderValue {
    let seconds = wait.as_secs() + u64::from(wait.subsec_nanos() > 0);
    axum::http::HeaderValue::from(seconds.max(1))
}

/// An error of the portal itself: the status as its code.
pub fn error(status: StatusCode, message: impl Into<String>) -> ApiError {
    ApiError(
        status,
        ErrorObject::rpc(i64::from(status.as_u16()), message),
        None,
    )
}

impl From<cloud_store::StoreError> for ApiError {
    fn from(e: cloud_store::StoreError) -> Self {
        tracing::error!(error = %e, "API request failed on the database");
        if e.is_unavailable() {
            error(StatusCode::SERVICE_UNAVAILABLE, "database unavailable")
        } else {
            error(StatusCode::INTERNAL_SERVER_ERROR, "database error")
        }
    }
}

/// The HTTP status of a gateway's NXg error: a missing object is 404, a refusal of rights or
/// identity 403, a node on the lift's bus that did not answer (SDO timeout) 504, anything else
/// the caller's mistake (400).
fn status_of(code: Option<ErrorCode>) -> StatusCode {
    match code {
        Some(ErrorCode::TIMEOUT) => StatusCode::GATEWAY_TIMEOUT,
        Some(ErrorCode::NO_OBJECT | ErrorCode::NO_SUB_INDEX) => StatusCode::NOT_FOUND,
        Some(ErrorCode::IDENTITY | ErrorCode::PRIVILEGE | ErrorCode::DEVICE_STATE) => {
            StatusCode::FORBIDDEN
        }
        _ => StatusCode::BAD_REQUEST,
    }
}

impl From<Failure> for ApiError {
    fn from(f: Failure) -> Self {
        match f {
            Failure::Error(e) => ApiError(status_of(e.abort_code()), e, None),
            Failure::Invalid(why) => error(
                StatusCode::BAD_GATEWAY,
                format!("the gateway's answer is not valid: {why}"),
            ),
            Failure::Timeout => error(
                StatusCode::GATEWAY_TIMEOUT,
                "the gateway did not answer in time",
            ),
            Failure::Busy => {
                let mut e = error(
                    StatusCode::TOO_MANY_REQUESTS,
                    "too many requests for this gateway",
                );
                e.2 = Some(std::time::Duration::from_secs(1));
                e
            }
            Failure::Gone => error(StatusCode::SERVICE_UNAVAILABLE, "the gateway is offline"),
        }
    }
}

/// A query string read into `T`; a malformed one answers 400 with an error object.
pub struct ApiQuery<T>(pub T);

impl<T: DeserializeOwned + Send, S: Send + Sync> FromRequestParts<S> for ApiQuery<T> {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, state: &S) -> Result<Self, ApiError> {
        axum::extract::Query::<T>::from_request_parts(parts, state)
            .await
            .map(|q| ApiQuery(q.0))
            .map_err(|e: QueryRejection| error(StatusCode::BAD_REQUEST, e.body_text()))
    }
}

/// A JSON body read into `T`; a malformed one answers with an error object (400, or 415 without
/// a JSON content type, 422 for a body of the wrong shape). A number with a zero fraction is
/// the integer it equals (`2.0` is 2): JSON has one number type, and the OpenAPI document's
/// `integer` is JSON Schema's, which holds `2.0` (JSON Schema 2020-12 §6.1.1).
pub struct ApiJson<T>(pub T);

impl<T: DeserializeOwned, S: Send + Sync> FromRequest<S> for ApiJson<T> {
    type Rejection = ApiError;

    async fn from_request(request: Request, state: &S) -> Result<Self, ApiError> {
        let Json(mut body) = Json::<serde_json::Value>::from_request(request, state)
            .await
            .map_err(|e: JsonRejection| error(e.status(), e.body_text()))?;
        integral(&mut body);
        serde_path_to_error::deserialize(body)
            .map(ApiJson)
            .map_err(|e| {
                error(
                    StatusCode::UNPROCESSABLE_ENTITY,
                    format!("Failed to deserialize the JSON body into the target type: {e}"),
                )
            })
    }
}

/// `value` with every number that has a zero fraction and fits an integer as that integer.
fn integral(value: &mut serde_json::Value) {
    use serde_json::Value;
    match value {
        Value::Number(n) if n.is_f64() => {
            let f = n.as_f64().unwrap_or(f64::NAN);
            // 2^64 and -2^63 are exact in an f64; between them an f64 without fraction is an
            // integer the casts keep exactly. Beyond, it stays a number (refused as out of range
            // by an integer field).
            if f.fract() == 0.0 && (0.0..18_446_744_073_709_551_616.0).contains(&f) {
                *n = (f as u64).into();
            } else if f.fract() == 0.0 && (-9_223_372_036_854_775_808.0..0.0).contains(&f) {
                *n = (f as i64).into();
            }
        }
        Value::Array(items) => items.iter_mut().for_each(integral),
        Value::Object(fields) => fields.values_mut().for_each(integral),
        _ => {}
    }
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    #[test]
    fn numbers_without_fraction_are_integers() {
        let mut body = json!({
            "privilege": 2.0,
            "inhibit": 1e19,
            "offset": -3.0,
            "threshold": 0.5,
            "huge": 1e300,
            "list": [29.0, {"net": 207.0}],
        });
        super::integral(&mut body);
        assert_eq!(
            body,
            json!({
                "privilege": 2,
                "inhibit": 10_000_000_000_000_000_000_u64,
                "offset": -3,
                "threshold": 0.5,
                "huge": 1e300,
                "list": [29, {"net": 207}],
            })
        );
        assert!(body["privilege"].is_u64() && body["offset"].is_i64() && body["huge"].is_f64());
    }
}
