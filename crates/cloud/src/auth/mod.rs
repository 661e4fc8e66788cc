//! Who may do what on the portal (docs/PORTAL.md §Users and roles): the caller of a request
//! ([`Caller`]: an API key, or the web UI's session with its CSRF token), its role and
//! account, the browser [`sessions`], the throttles of keys and sign-ins
//! ([`crate::throttle`]), who elevated which lift ([`elevation`]) and single sign-on
//! ([`oidc`]).

pub mod elevation;
pub mod oidc;
pub mod passwords;
pub mod sessions;

use std::sync::{Arc, Mutex};

use axum::extract::FromRequestParts;
use axum::http::request::Parts;
use axum::http::{Method, StatusCode};
use cloud_types::users::{Operator, Role};

use crate::errors::{error, ApiError};
use crate::throttle::{KeyRates, SignIns};
use cloud_store::Store;
use elevation::Elevations;
use sessions::Sessions;

/// What the caller's extractor needs of the state of the handlers it serves.
pub trait AuthState: Send + Sync {
    /// Sessions, throttles, elevations.
    fn auth(&self) -> &Auth;
    /// The database (API keys, users).
    fn store(&self) -> &Store;
}

/// The portal's authentication and authorisation state.
pub struct Auth {
    /// Signed-in browsers of the web UI.
    pub sessions: Sessions,
    /// Requests per API key (`[server] requests_per_key_s`).
    pub key_rates: Mutex<KeyRates>,
    /// Failed web sign-ins per source address, and per user name at an address.
    pub sign_ins: Mutex<SignIns>,
    /// Where sign-in secrets are checked.
    pub passwords: passwords::PasswordChecks,
    /// Who elevated which lift.
    pub elevations: Elevations,
    /// Single sign-on (`[oidc]`), if configured.
    pub sso: Option<Arc<oidc::Sso>>,
}

/// The operator a request acts for: `Authorization: Bearer API_KEY`, or the web UI's session
/// cookie. A cookie alone never authorises a change: requests other than GET must also carry
/// the session's `X-CSRF-Token`, which another site cannot read.
pub struct Caller(pub Operator);

impl<S: AuthState> FromRequestParts<Arc<S>> for Caller {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, app: &Arc<S>) -> Result<Self, ApiError> {
        let header = |name: &str| parts.headers.get(name).and_then(|v| v.to_str().ok());
        if let Some(key) = header("authorization").and_then(|v| v.strip_prefix("Bearer ")) {
            let key = key.trim();
            let operator = app
                .store()
                .operator_by_key(key)
                .await?
                .ok_or_else(|| error(StatusCode::UNAUTHORIZED, "unknown API key"))?;
            let within = app
                .auth()
                .key_rates
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .take(&cloud_store::digest(key), std::time::Instant::now());
            return match within {
                Ok(()) => Ok(Caller(operator)),
                Err(wait) => {
                    let mut e = error(
                        StatusCode::TOO_MANY_REQUESTS,
                        "too many requests with this API key ([server] requests_per_key_s)",
                    );
                    e.2 = Some(wait);
                    Err(e)
                }
            };
        }
        let Some(session) = app
            .auth()
            .sessions
            .current(&parts.headers, app.store())
            .await?
        else {
            return Err(error(
                StatusCode::UNAUTHORIZED,
                "Authorization: Bearer API_KEY is required",
            ));
        };
        let reads = parts.method == Method::GET || parts.method == Method::HEAD;
        if !reads && !session.csrf_matches(header("x-csrf-token")) {
            return Err(error(
                StatusCode::FORBIDDEN,
                "X-CSRF-Token missing or wrong",
            ));
        }
        Ok(Caller(session.operator))
    }
}

/// The caller, if its role includes `role` (docs/PORTAL.md §Users and roles); 403 otherwise.
pub fn allowed(caller: Caller, role: Role) -> Result<Operator, ApiError> {
    let operator = caller.0;
    if operator.may(role) {
        return Ok(operator);
    }
    Err(error(
        StatusCode::FORBIDDEN,
        format!(
            "{} is {} {}; this needs the role {role}",
            operator.user,
            if operator.role == Role::Admin {
                "an"
            } else {
                "a"
            },
            operator.role
        ),
    ))
}
