//! The account's users and API keys through the REST API (docs/PORTAL.md §Users and roles), for
//! its administrators: the same operations as `canlift cloud user|key`, scoped to the caller's
//! own account. Secrets and keys are shown once, in the answer that makes them.

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::Json;
use nxg::msg::ErrorObject;
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

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
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct NewUser {
    /// Unique within the account.
    #[schema(pattern = "^[A-Za-z0-9._@-]{1,64}$")]
    name: String,
    /// What the user may do.
    role: Role,
}

/// The body of `PUT /api/v1/users/{name}/role`.
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct NewRole {
    /// The role from now on.
    role: Role,
}

/// A user with its sign-in secret, shown once.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub(super) struct UserSecret {
    /// The user.
    user: String,
    /// Its account.
    account: String,
    /// Its role.
    role: Role,
    /// The sign-in secret, shown only now.
    secret: String,
}

/// The body of `POST /api/v1/keys`.
#[derive(Debug, Clone, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub(super) struct NewKey {
    /// The user the key acts for, with its role.
    user: String,
    /// Days it works (absent or null: until revoked).
    #[serde(default)]
    #[schema(minimum = 1, maximum = 36500)]
    expires_days: Option<u32>,
}

/// A new key, shown once.
#[derive(Debug, Clone, Serialize, ToSchema)]
pub(super) struct KeySecret {
    /// The key, shown only now.
    api_key: String,
    /// Its id (for revoking it).
    id: String,
}

/// Longest user name.
const NAME_MAX: usize = 64;

/// The account's users.
#[utoipa::path(get, path = "/api/v1/users", operation_id = "listUsers", tag = "users",
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 200, description = "the users", body = Vec<User>)))]
pub(super) async fn list(
    State(app): State<Arc<AppState>>,
    caller: Caller,
) -> Result<Json<Vec<User>>, ApiError> {
    let admin = allowed(caller, Role::Admin)?;
    Ok(Json(app.store.users(&admin.account.name).await?))
}

/// Add a user; its sign-in secret is in the answer, shown only now.
#[utoipa::path(post, path = "/api/v1/users", operation_id = "addUser", tag = "users",
    request_body(content((NewUser = "application/json", example = json!({"name": "ann", "role": "engineer"})))),
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 201, description = "added", body = UserSecret),
        (status = 400, description = "a malformed name", body = ErrorObject),
        (status = 409, description = "the account has a user of that name (names are unique within their account)", body = ErrorObject)))]
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

/// Give a user another role.
#[utoipa::path(put, path = "/api/v1/users/{name}/role", operation_id = "setUserRole", tag = "users",
    params(("name" = String, Path, description = "the user", example = "ann")),
    request_body(content((NewRole = "application/json", example = json!({"role": "technician"})))),
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 204, description = "changed"), super::document::NoSuchUser))]
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

/// Disable a user: its keys and sessions stop working within a second.
#[utoipa::path(post, path = "/api/v1/users/{name}/disable", operation_id = "disableUser",
    tag = "users", params(("name" = String, Path, description = "the user", example = "ann")),
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 204, description = "disabled"), super::document::NoSuchUser))]
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

/// A new sign-in secret for a user, shown only now; the old one stops working.
#[utoipa::path(post, path = "/api/v1/users/{name}/reset", operation_id = "resetUserSecret",
    tag = "users", params(("name" = String, Path, description = "the user", example = "ann")),
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 200, description = "the new secret", body = UserSecret), super::document::NoSuchUser))]
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

/// The account's users' API keys (never the keys themselves).
#[utoipa::path(get, path = "/api/v1/keys", operation_id = "listKeys", tag = "users",
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 200, description = "the keys", body = Vec<KeyInfo>)))]
pub(super) async fn keys(
    State(app): State<Arc<AppState>>,
    caller: Caller,
) -> Result<Json<Vec<KeyInfo>>, ApiError> {
    let admin = allowed(caller, Role::Admin)?;
    Ok(Json(app.store.keys(&admin.account.name).await?))
}

/// A new API key acting for a user with its role, shown only now.
#[utoipa::path(post, path = "/api/v1/keys", operation_id = "addKey", tag = "users",
    request_body(content((NewKey = "application/json", example = json!({"user": "ann", "expires_days": 90})))),
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 201, description = "made", body = KeySecret),
        (status = 400, description = "expires_days beyond its bounds", body = ErrorObject),
        super::document::NoSuchUser))]
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

/// Revoke a key: it stops working within a second.
#[utoipa::path(delete, path = "/api/v1/keys/{id}", operation_id = "revokeKey", tag = "users",
    params(("id" = String, Path, description = "the key's id", example = "0123456789ab")),
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 204, description = "revoked"), super::document::NoSuchUser))]
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
