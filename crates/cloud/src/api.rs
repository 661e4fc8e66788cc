//! The operator REST API (`/api/v1/…`, JSON, `Authorization: Bearer API_KEY`). A lift's id is
//! `VENDORID-PRODUCTCODE-SERNUM`; an account sees only the lifts of its own domain (404 for
//! others). NXg errors come back as 4xx with `{"code", "message", "data"}`; an offline gateway
//! gives 503, a gateway that does not answer in time 504. Puts and elevations are audited.

use std::collections::HashMap;
use std::convert::Infallible;
use std::sync::Arc;

use axum::extract::FromRequestParts;
use axum::extract::{Path, Query, State};
use axum::http::request::Parts;
use axum::http::{Method, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use futures_util::Stream;
use nxg::mplex::Mplex;
use nxg::portal::Failure;
use serde::Deserialize;
use serde_json::{json, Value};

use crate::config::DashboardSection;
use crate::gateways::{event_json, Registry};
use crate::store::{self, Account, AuditEntry, Store};
use crate::web::Sessions;

/// What the handlers share.
pub struct App {
    /// The database.
    pub store: Store,
    /// Live gateways.
    pub registry: Arc<Registry>,
    /// Signed-in browsers of the web UI.
    pub sessions: Sessions,
    /// What the web UI shows (mplexes normalized).
    pub dashboard: Arc<DashboardSection>,
}

/// An error answer.
pub struct ApiError(StatusCode, Value);

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        (self.0, Json(self.1)).into_response()
    }
}

fn error(status: StatusCode, message: &str) -> ApiError {
    ApiError(status, json!({"code": status.as_u16(), "message": message}))
}

impl From<store::StoreError> for ApiError {
    fn from(e: store::StoreError) -> Self {
        tracing::error!(error = %e, "API request failed on the database");
        error(StatusCode::INTERNAL_SERVER_ERROR, "database unavailable")
    }
}

impl From<Failure> for ApiError {
    fn from(f: Failure) -> Self {
        match f {
            Failure::Error(e) => {
                let code = e.get("code").and_then(Value::as_i64).unwrap_or(0);
                let status = match code {
                    0x0602_0000 | 0x0609_0011 => StatusCode::NOT_FOUND,
                    0x0800_0020 | 0x0800_0021 => StatusCode::FORBIDDEN,
                    _ => StatusCode::BAD_REQUEST,
                };
                ApiError(status, e)
            }
            Failure::Timeout => error(
                StatusCode::GATEWAY_TIMEOUT,
                "the gateway did not answer in time",
            ),
            Failure::Busy => error(
                StatusCode::TOO_MANY_REQUESTS,
                "too many requests for this gateway",
            ),
            Failure::Gone => error(StatusCode::SERVICE_UNAVAILABLE, "the gateway is offline"),
        }
    }
}

/// The account a request acts for: `Authorization: Bearer API_KEY`, or the web UI's session
/// cookie. A cookie alone never authorises a change: requests other than GET must also carry
/// the session's `X-CSRF-Token`, which another site cannot read.
pub struct Caller(pub Account);

impl FromRequestParts<Arc<App>> for Caller {
    type Rejection = ApiError;

    async fn from_request_parts(parts: &mut Parts, app: &Arc<App>) -> Result<Self, ApiError> {
        let header = |name: &str| parts.headers.get(name).and_then(|v| v.to_str().ok());
        if let Some(key) = header("authorization").and_then(|v| v.strip_prefix("Bearer ")) {
            return app
                .store
                .account_by_key(key.trim())
                .await?
                .map(Caller)
                .ok_or_else(|| error(StatusCode::UNAUTHORIZED, "unknown API key"));
        }
        let Some(session) = app.sessions.get(&parts.headers) else {
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
        Ok(Caller(session.account))
    }
}

/// The caller's account, if the lift is one of the account's (404 otherwise).
async fn lift_of(app: &App, caller: Caller, id: &str) -> Result<Account, ApiError> {
    let account = caller.0;
    if app.store.lift(&account.domain, id).await?.is_none() {
        return Err(error(StatusCode::NOT_FOUND, "no such lift"));
    }
    Ok(account)
}

fn mplex(text: &str) -> Result<Mplex, ApiError> {
    Mplex::parse(text).map_err(|e| error(StatusCode::BAD_REQUEST, &e.to_string()))
}

async fn lifts(
    State(app): State<Arc<App>>,
    Caller(account): Caller,
) -> Result<Json<Value>, ApiError> {
    let lifts: Vec<Value> = app
        .store
        .lifts(&account.domain)
        .await?
        .into_iter()
        .map(|l| {
            let online = app.registry.online(&l.id);
            let mut v = serde_json::to_value(&l).unwrap_or_default();
            v["online"] = json!(online);
            v
        })
        .collect();
    Ok(Json(json!(lifts)))
}

#[derive(Debug, Deserialize)]
struct GetQuery {
    lang: Option<String>,
    alt_lang: Option<String>,
    form: Option<String>,
    compact: Option<bool>,
    node: Option<u8>,
    net: Option<u8>,
    datatype: Option<u32>,
}

fn node_param(node: Option<u8>, net: Option<u8>, datatype: Option<u32>) -> Option<Value> {
    node.map(|id| {
        let mut n = json!({"id": id, "net": net.unwrap_or(1)});
        if let Some(t) = datatype {
            n["datatype"] = json!(t);
        }
        n
    })
}

/// `get_canopen_object` parameters (NXg §6.1) in `form` `full`, `stripped` or `naked`.
pub(crate) fn read_params(mplex: &str, lang: &str, alt: &str, form: &str) -> Value {
    let mut object = json!({"mplex": mplex});
    if form != "full" {
        object[form] = json!(true);
    }
    json!({
        "lang": {"preferred_language": lang, "alternate_language": alt},
        "object": object,
    })
}

async fn get_object(
    State(app): State<Arc<App>>,
    caller: Caller,
    Path((id, text)): Path<(String, String)>,
    Query(q): Query<GetQuery>,
) -> Result<Json<Value>, ApiError> {
    lift_of(&app, caller, &id).await?;
    mplex(&text)?;
    let form = match q.form.as_deref() {
        None | Some("full") => "full",
        Some(f @ ("stripped" | "naked")) => f,
        Some(other) => {
            return Err(error(
                StatusCode::BAD_REQUEST,
                &format!("form {other:?}: full, stripped or naked"),
            ))
        }
    };
    let lang = q.lang.as_deref().unwrap_or("en");
    let alt = q.alt_lang.as_deref().unwrap_or("en");
    let mut params = read_params(&text, lang, alt, form);
    params["object"]["compact"] = json!(q.compact.unwrap_or(false));
    if let Some(node) = node_param(q.node, q.net, q.datatype) {
        params["node"] = node;
    }
    Ok(Json(
        app.registry.call(&id, "get_canopen_object", params).await?,
    ))
}

#[derive(Debug, Deserialize)]
struct PutBody {
    value: String,
    datatype: u32,
    physunit: u32,
    node: Option<u8>,
    net: Option<u8>,
}

async fn put_object(
    State(app): State<Arc<App>>,
    caller: Caller,
    Path((id, text)): Path<(String, String)>,
    Json(body): Json<PutBody>,
) -> Result<Json<Value>, ApiError> {
    let account = lift_of(&app, caller, &id).await?;
    mplex(&text)?;
    let sernum = app.registry.sernum(&id).ok_or(Failure::Gone)?;
    let node = node_param(body.node, body.net, None);
    // The value before, for the audit log (best effort: a write-only object has none).
    let mut read = json!({"object": {"mplex": text, "naked": true}});
    if let Some(n) = &node {
        read["node"] = n.clone();
        read["node"]["datatype"] = json!(body.datatype);
    }
    let old = app
        .registry
        .call(&id, "get_canopen_object", read)
        .await
        .ok()
        .and_then(|v| v["object"]["value"][0].as_str().map(str::to_owned));
    let mut params = json!({
        "sernum": sernum,
        "object": {"mplex": text, "datatype": body.datatype, "physunit": body.physunit, "value": body.value},
    });
    if let Some(n) = node {
        params["node"] = n;
    }
    let result = app.registry.call(&id, "put_canopen_object", params).await;
    let entry = AuditEntry {
        at: store::now_ms(),
        account: account.name,
        lift: id,
        action: "put".into(),
        object: text,
        old_value: old,
        new_value: body.value,
        result: outcome(&result),
    };
    app.store.audit(&entry).await?;
    Ok(Json(result?))
}

fn outcome(result: &Result<Value, Failure>) -> String {
    match result {
        Ok(_) => "ok".into(),
        Err(Failure::Error(e)) => format!("error {}", e["code"]),
        Err(f) => format!("{f:?}").to_lowercase(),
    }
}

#[derive(Debug, Deserialize)]
struct PrivilegeBody {
    privilege: u8,
    password: String,
}

async fn privilege(
    State(app): State<Arc<App>>,
    caller: Caller,
    Path(id): Path<String>,
    Json(body): Json<PrivilegeBody>,
) -> Result<Json<Value>, ApiError> {
    let account = lift_of(&app, caller, &id).await?;
    let sernum = app.registry.sernum(&id).ok_or(Failure::Gone)?;
    // NXg §6.4: the gateway compares the unsalted SHA-1; the password itself is never stored.
    let sha1 = ring::digest::digest(
        &ring::digest::SHA1_FOR_LEGACY_USE_ONLY,
        body.password.as_bytes(),
    );
    let passhash = store::hex(sha1.as_ref());
    let params = json!({"sernum": sernum, "privilege": body.privilege, "passhash": passhash});
    let result = app.registry.call(&id, "elevate_privilege", params).await;
    let entry = AuditEntry {
        at: store::now_ms(),
        account: account.name,
        lift: id,
        action: "elevate".into(),
        object: "privilege".into(),
        old_value: None,
        new_value: body.privilege.to_string(),
        result: outcome(&result),
    };
    app.store.audit(&entry).await?;
    Ok(Json(result?))
}

#[derive(Debug, Deserialize)]
struct SubscriptionBody {
    mplex: Vec<String>,
    inhibit: Option<u64>,
    threshold: Option<f64>,
}

/// `reg_canopen_object` (POST) or `unreg_canopen_object` (DELETE).
async fn subscriptions(
    State(app): State<Arc<App>>,
    method: axum::http::Method,
    caller: Caller,
    Path(id): Path<String>,
    Json(body): Json<SubscriptionBody>,
) -> Result<Json<Value>, ApiError> {
    lift_of(&app, caller, &id).await?;
    let (rpc, params) = if method == axum::http::Method::DELETE {
        ("unreg_canopen_object", json!({"mplex": body.mplex}))
    } else {
        let params = json!({"mplex": body.mplex, "inhibit": body.inhibit.unwrap_or(0), "threshold": body.threshold.unwrap_or(0.0)});
        ("reg_canopen_object", params)
    };
    Ok(Json(app.registry.call(&id, rpc, params).await?))
}

async fn events(
    State(app): State<Arc<App>>,
    caller: Caller,
    Path(id): Path<String>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    lift_of(&app, caller, &id).await?;
    let rx = app.registry.subscribe(&id);
    let online = app.registry.online(&id);
    let first = Event::default()
        .event("online")
        .data(json!({"lift": id, "online": online}).to_string());
    let stream =
        futures_util::stream::unfold((rx, Some(first), id), |(mut rx, first, id)| async move {
            if let Some(first) = first {
                return Some((Ok(first), (rx, None, id)));
            }
            loop {
                match rx.recv().await {
                    Ok(event) => {
                        let (kind, data) = event_json(&id, &event);
                        return Some((Ok(Event::default().event(kind).data(data)), (rx, None, id)));
                    }
                    Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => continue,
                    Err(tokio::sync::broadcast::error::RecvError::Closed) => return None,
                }
            }
        });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

async fn history(
    State(app): State<Arc<App>>,
    caller: Caller,
    Path((id, text)): Path<(String, String)>,
    Query(q): Query<HashMap<String, i64>>,
) -> Result<Json<Value>, ApiError> {
    lift_of(&app, caller, &id).await?;
    let m = mplex(&text)?;
    let to = q.get("to").copied().unwrap_or(i64::MAX);
    let from = q.get("from").copied().unwrap_or(0);
    let rows = app.store.history(&id, &m.to_string(), from, to).await?;
    let values: Vec<Value> = rows
        .into_iter()
        .map(|(at, v)| json!({"at": at, "value": v}))
        .collect();
    Ok(Json(
        json!({"lift": id, "mplex": m.to_string(), "values": values}),
    ))
}

async fn audit(
    State(app): State<Arc<App>>,
    Caller(account): Caller,
) -> Result<Json<Value>, ApiError> {
    Ok(Json(json!(app.store.audit_log(&account.domain).await?)))
}

async fn openapi() -> Json<Value> {
    Json(serde_json::from_str(OPENAPI).unwrap_or_default())
}

/// The OpenAPI document of this API.
pub const OPENAPI: &str = include_str!("openapi.json");

/// The `/api/v1` routes.
pub fn routes(app: Arc<App>) -> Router {
    Router::new()
        .route("/api/v1/openapi.json", get(openapi))
        .route("/api/v1/lifts", get(lifts))
        .route(
            "/api/v1/lifts/{id}/objects/{mplex}",
            get(get_object).put(put_object),
        )
        .route("/api/v1/lifts/{id}/objects/{mplex}/history", get(history))
        .route(
            "/api/v1/lifts/{id}/privilege",
            axum::routing::post(privilege),
        )
        .route(
            "/api/v1/lifts/{id}/subscriptions",
            axum::routing::post(subscriptions).delete(subscriptions),
        )
        .route("/api/v1/lifts/{id}/events", get(events))
        .route("/api/v1/audit", get(audit))
        .with_state(app)
}
