//! The account's users and API keys through the REST API (docs/PORTAL.md §Users and roles), for
//! its administrators: the same operations as `canlift cloud user|key`, scoped to the caller's
//! own account. Secrets and keys are shown once, in the answer that makes them.

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::Json;
use serde::{Deserialize, Serialize};

use crate::auth::{allowed, Caller};
use crate::errors::{error, ApiError, ApiJson};
use crate::state::AppState;
use cloud_types::users::{KeyInfo, Role, User};

use cloud_store::UserError;

impl From<UserError> for ApiError {
    fn from(e: UserError) -> Self {
        match e {
            UserError::Store(e) => e.into(),
            UserError::Taken(_) => error(StatusCode::CONFLICT, e.to_string()),
            UserError::NoAccount(_) | UserError::NoUser(..) | UserError::NoKey(..) => {
                error(StatusCode::NOT_FOUND, e.to_string())
            }
        }
    }
}

/// The body of `POST /api/v1/users`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct NewUser {
    name: String,
    role: Role,
}

/// The body of `PUT /api/v1/users/{name}/role`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct NewRole {
    role: Role,
}

/// A user with its sign-in secret, shown once.
#[derive(Debug, Clone, Serialize)]
pub(super) struct UserSecret {
    user: String,
    account: String,
    role: Role,
    secret: String,
}

/// The body of `POST /api/v1/keys`.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct NewKey {
    user: String,
    /// Days it works (absent: until revoked).
    #[serde(default)]
    expires_days: Option<u32>,
}

/// A new key, shown once.
#[derive(Debug, Clone, Serialize)]
pub(super) struct KeySecret {
    api_key: String,
    id: String,
}

/// Longest user name.
const NAME_MAX: usize = 64;

/// `GET /api/v1/users`.
pub(super) async fn list(
    State(app): State<Arc<AppState>>,
    caller: Caller,
) -> Result<Json<Vec<User>>, ApiError> {
    let admin = allowed(caller, Role::Admin)?;
    Ok(Json(app.store.users(&admin.account.name).await?))
}

/// `POST /api/v1/users`: 201 with the secret; 409 when the account has a user of the name.
pub(super) async fn add(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    ApiJson(body): ApiJson<NewUser>,
) -> Result<(StatusCode, Json<UserSecret>), ApiError> {
    let admin = allowed(caller, Role::Admin)?;
    let name = body.name.trim();
    let fine = |c: char| c.is_alphanumeric() || "._@-".contains(c);
    if name.is_empty() || name.chars().count() > NAME_MAX || !name.chars().all(fine) {
        return Err(error(
            StatusCode::BAD_REQUEST,
            "name: 1–64 letters, digits, '.', '_', '@' or '-'",
        ));
    }
    let account = admin.account.name;
    let secret = app.store.add_user(&account, name, body.role).await?;
    tracing::info!(by = %admin.user, user = name, role = %body.role, "user added");
    let made = UserSecret {
        user: name.to_owned(),
        account,
        role: body.role,
        secret,
    };
    Ok((StatusCode::CREATED, Json(made)))
}

/// `PUT /api/v1/users/{name}/role`.
pub(super) async fn role(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(name): Path<String>,
    ApiJson(body): ApiJson<NewRole>,
) -> Result<StatusCode, ApiError> {
    let admin = allowed(caller, Role::Admin)?;
    app.store
        .set_role(&admin.account.name, &name, body.role)
        .await?;
    tracing::info!(by = %admin.user, user = %name, role = %body.role, "role changed");
    Ok(StatusCode::NO_CONTENT)
}

/// `POST /api/v1/users/{name}/disable`: its keys and sessions stop working.
pub(super) async fn disable(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(name): Path<String>,
) -> Result<StatusCode, ApiError> {
    let admin = allowed(caller, Role::Admin)?;
    app.store.disable_user(&admin.account.name, &name).await?;
    tracing::info!(by = %admin.user, user = %name, "user disabled");
    Ok(StatusCode::NO_CONTENT)
}

/// `POST /api/v1/users/{name}/reset`: a new sign-in secret, shown once.
pub(super) async fn reset(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(name): Path<String>,
) -> Result<Json<UserSecret>, ApiError> {
    let admin = allowed(caller, Role::Admin)?;
    let account = admin.account.name;
    let (secret, role) = app.store.reset_user(&account, &name).await?;
    tracing::info!(by = %admin.user, user = %name, "secret reset");
    Ok(Json(UserSecret {
        user: name,
        account,
        role,
        secret,
    }))
}

/// `GET /api/v1/keys`.
pub(super) async fn keys(
    State(app): State<Arc<AppState>>,
    caller: Caller,
) -> Result<Json<Vec<KeyInfo>>, ApiError> {
    let admin = allowed(caller, Role::Admin)?;
    Ok(Json(app.store.keys(&admin.account.name).await?))
}

/// `POST /api/v1/keys`: 201 with the key, shown once.
pub(super) async fn add_key(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    ApiJson(body): ApiJson<NewKey>,
) -> Result<(StatusCode, Json<KeySecret>), ApiError> {
    let admin = allowed(caller, Role::Admin)?;
    let expires = super::bounded("expires_days", body.expires_days, 1..=36_500)?
        .map(|days| cloud_types::now_ms().saturating_add(i64::from(days) * 86_400_000));
    let (id, api_key) = app
        .store
        .add_key(&admin.account.name, &body.user, expires)
        .await?;
    tracing::info!(by = %admin.user, user = %body.user, key = %id, "API key added");
    Ok((StatusCode::CREATED, Json(KeySecret { api_key, id })))
}

/// `DELETE /api/v1/keys/{id}`: it stops working.
pub(super) async fn revoke(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    let admin = allowed(caller, Role::Admin)?;
    app.store.revoke_key(&admin.account.name, &id).await?;
    tracing::info!(by = %admin.user, key = %id, "API key revoked");
    Ok(StatusCode::NO_CONTENT)
}
