//! The operator REST API (`/api/v1/…`, JSON, `Authorization: Bearer API_KEY`). A lift's id is
//! `VENDORID-PRODUCTCODE-SERNUM`; an account sees only the lifts of its own domain (404 for
//! others). NXg errors come back as 4xx with the gateway's error object; an offline gateway
//! gives 503, a gateway that does not answer in time 504. Puts and elevations are audited. The
//! bodies are the types of [`cloud_types::api`]; alarms and the event log are in `alarms`, users
//! and keys in `users`, availability reports in `reports`; who the caller is and what it may do in [`crate::auth`].

mod alarms;
mod document;
mod idempotency;
mod reports;
mod users;

use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::extract::{ConnectInfo, Path, State};
use axum::http::StatusCode;
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::routing::get;
use axum::{Json, Router};
use document::{GatewayAway, NoLift, NoObject, WriteRefused};
use futures_util::Stream;
use nxg::msg::{
    Done, ElevateAnswer, ElevateParams, ErrorObject, Lang, MplexText, NodeId, NodeRef,
    ObjectAnswer, PutAnswer, PutObject, PutParams, TokenParams,
};
use nxg::names::ObjectNames;
use nxg::portal::Failure;
use utoipa_axum::router::OpenApiRouter;
use utoipa_axum::routes;

use crate::auth::{allowed, Caller};
use crate::errors::{error, ApiError, ApiJson, ApiQuery};
use crate::gateways::subscriptions::{Subscriptions, WhenOffline};
use crate::state::AppState;
use cloud_types::api::{
    EventsQuery, Form, GetQuery, History, HistoryPoint, HistoryQuery, LiftSummary, NameQuery,
    PrivilegeBody, PutBody, SubscriptionBody, UnsubscribeBody, HISTORY_POINTS, HISTORY_POINTS_MAX,
};
use cloud_types::audit::{AuditEntry, PENDING};
use cloud_types::lifts::shown_id;
use cloud_types::subscriptions::{Subscriber, Terms};
use cloud_types::users::{Account, Operator, Role};

/// The caller, if its role includes `role` (403 otherwise), and the registry's key of lift
/// `id` of its account (404 when the account has no such lift): an id names a lift within the
/// caller's account only (docs/PORTAL.md §Lifts and accounts).
pub async fn lift_of(
    app: &AppState,
    caller: Caller,
    id: &str,
    role: Role,
) -> Result<(Operator, String), ApiError> {
    let operator = allowed(caller, role)?;
    match key_of(app, &operator.account, id).await? {
        Some(key) => Ok((operator, key)),
        None => Err(error(StatusCode::NOT_FOUND, "no such lift")),
    }
}

/// The registry's key of lift `id` of `account`, if it has one.
pub(crate) async fn key_of(
    app: &AppState,
    account: &Account,
    id: &str,
) -> Result<Option<String>, ApiError> {
    // A connected lift's account is known without the database (and without a query per
    // request).
    for key in cloud_types::lifts::keys_of(id, &account.name) {
        if app.registry.serves(&account.domain, &key) {
            return Ok(Some(key));
        }
    }
    Ok(app.store.lift(account, id).await?.map(|record| record.id))
}

/// The object of a path or `?name=`: an mplex as the gateway spells it is passed on as written
/// (its answer echoes it); the other address forms (`0x6520:1`, `6520sub1`) and object names
/// (`Trip counter`: case-insensitive, a unique prefix) in the gateway's spelling
/// (docs/PROTOCOL.md §Mplex).
pub(crate) fn mplex(names: &ObjectNames, text: &str) -> Result<MplexText, ApiError> {
    use nxg::mplex::Mplex;
    match Mplex::parse(text) {
        Ok(mplex) => Ok(MplexText {
            mplex,
            text: text.to_owned(),
        }),
        Err(_) => names
            .resolve(text)
            .map(MplexText::from)
            .map_err(|e| error(StatusCode::BAD_REQUEST, e.to_string())),
    }
}

/// `value` if it is in `range` (or absent); else 400 naming the parameter and its range, as
/// the OpenAPI document states it — nothing beyond a documented bound is taken silently.
pub(crate) fn bounded<T: PartialOrd + std::fmt::Display + Copy>(
    what: &str,
    value: Option<T>,
    range: std::ops::RangeInclusive<T>,
) -> Result<Option<T>, ApiError> {
    match value {
        Some(v) if !range.contains(&v) => Err(error(
            StatusCode::BAD_REQUEST,
            format!("{what}: {} to {}", range.start(), range.end()),
        )),
        v => Ok(v),
    }
}

fn node(node: Option<u8>, net: Option<u8>) -> Result<Option<NodeRef>, ApiError> {
    let net = bounded("net", net, 1..=255)?;
    node.map(|id| {
        let id = NodeId::new(id)
            .ok_or_else(|| error(StatusCode::BAD_REQUEST, "node: a node-ID 1–127"))?;
        Ok(NodeRef::new(id, net.unwrap_or(1)))
    })
    .transpose()
}

/// A lift in a path, as its account knows it.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Path)]
pub(crate) struct LiftPath {
    /// The lift: VENDORID-PRODUCTCODE-SERNUM.
    #[param(
        pattern = "^[0-9]+-[0-9]+-[^/]+$",
        example = "1050-4096-180917010200000102"
    )]
    id: String,
}

/// An object of a lift in a path.
#[derive(Debug, serde::Deserialize, utoipa::IntoParams)]
#[into_params(parameter_in = Path)]
pub(crate) struct ObjectPath {
    /// The lift: VENDORID-PRODUCTCODE-SERNUM.
    #[param(
        pattern = "^[0-9]+-[0-9]+-[^/]+$",
        example = "1050-4096-180917010200000102"
    )]
    id: String,
    /// The object: 0x652001, 652001, 0x6520:1, 6520sub1, an index alone (sub-index 0), or a
    /// name of the CiA 417 catalog (any case, a unique prefix).
    #[param(example = "0x652001")]
    mplex: String,
}

/// The account's lifts: identity, liftnum, online, last_seen, api.
#[utoipa::path(get, path = "/api/v1/lifts", operation_id = "listLifts", tag = "lifts",
    extensions(("x-least-role" = json!("viewer"))),
    responses((status = 200, description = "the lifts", body = Vec<LiftSummary>)))]
async fn lifts(
    State(app): State<Arc<AppState>>,
    caller: Caller,
) -> Result<Json<Vec<LiftSummary>>, ApiError> {
    let operator = allowed(caller, Role::Viewer)?;
    let lifts = app
        .store
        .lifts(&operator.account.domain)
        .await?
        .into_iter()
        .map(|mut record| {
            let online = app.registry.online(&record.id);
            record.id = shown_id(&record.id).to_owned();
            LiftSummary { online, record }
        })
        .collect();
    Ok(Json(lifts))
}

/// Retire the lift: its registry entry and everything stored of it (telemetry, roll-ups, bus
/// events, alarms, subscriptions) are removed in one transaction, audited; its gateway, if
/// connected, is closed and its next CONNECT is a first contact (docs/PORTAL.md §Lifts and
/// accounts).
#[utoipa::path(delete, path = "/api/v1/lifts/{id}", operation_id = "retireLift", tag = "lifts",
    // An example no lift has: a contract test does not retire the lift it tests the rest on.
    params(("id" = String, Path, description = "the lift: VENDORID-PRODUCTCODE-SERNUM",
        pattern = "^[0-9]+-[0-9]+-[^/]+$", example = "1050-4096-RETIRED-EXAMPLE")),
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 204, description = "retired"), NoLift))]
async fn retire(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    let (operator, key) = lift_of(&app, caller, &id, Role::Admin).await?;
    if !app
        .store
        .retire(&operator.account, &key, &operator.user)
        .await?
    {
        return Err(error(StatusCode::NOT_FOUND, "no such lift"));
    }
    app.registry.retired(&key);
    tracing::info!(lift = %id, account = %operator.account.name, by = %operator.user, "lift retired");
    Ok(StatusCode::NO_CONTENT)
}

/// `get_canopen_object` on the lift (NXg §6.1).
#[utoipa::path(get, path = "/api/v1/lifts/{id}/objects/{mplex}", operation_id = "getObject",
    tag = "objects", params(ObjectPath, GetQuery),
    extensions(("x-least-role" = json!("viewer"))),
    responses((status = 200, description = "the gateway's answer", body = ObjectAnswer),
        (status = 400, description = "not an object address, or an unknown or ambiguous name; or the gateway's refusal with its NXg error", body = ErrorObject),
        NoObject, GatewayAway))]
async fn get_object(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(ObjectPath { id, mplex: text }): Path<ObjectPath>,
    ApiQuery(q): ApiQuery<GetQuery>,
) -> Result<Json<ObjectAnswer>, ApiError> {
    let (_, id) = lift_of(&app, caller, &id, Role::Viewer).await?;
    let lang = Lang::new(
        q.lang.as_deref().unwrap_or("en"),
        q.alt_lang.as_deref().unwrap_or("en"),
    );
    let mut params = q
        .form
        .unwrap_or_default()
        .get(mplex(&app.names, &text)?, lang);
    params.object.compact = q.compact.unwrap_or(false);
    params.node = node(q.node, q.net)?.map(|n| NodeRef {
        datatype: q.datatype,
        ..n
    });
    Ok(Json(app.registry.call(&id, &params).await?))
}

/// `put_canopen_object` on the lift (NXg §6.3), audited.
#[utoipa::path(put, path = "/api/v1/lifts/{id}/objects/{mplex}", operation_id = "putObject",
    tag = "objects", params(ObjectPath),
    request_body(content((PutBody = "application/json", example = json!({"value": "2", "datatype": 7, "physunit": 0})))),
    extensions(("x-least-role" = json!("technician"))),
    responses((status = 200, description = "the gateway's answer", body = PutAnswer),
        (status = 400, description = "not an object address, or an unknown or ambiguous name; or the gateway's refusal of the value with its NXg error", body = ErrorObject),
        WriteRefused, NoObject, GatewayAway))]
async fn put_object(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    ConnectInfo(client): ConnectInfo<SocketAddr>,
    Path(ObjectPath { id, mplex: text }): Path<ObjectPath>,
    ApiJson(body): ApiJson<PutBody>,
) -> Result<Json<PutAnswer>, ApiError> {
    let (operator, id) = lift_of(&app, caller, &id, Role::Technician).await?;
    let object = mplex(&app.names, &text)?;
    let sernum = app.registry.sernum(&id).ok_or(Failure::Gone)?;
    let node = node(body.node, body.net)?;
    // The value before, for the audit log, and the privilege writing needs (best effort: a
    // write-only object has no value, an object without metadata no privilege).
    let mut read = Form::Stripped.get(object.clone(), Lang::default());
    read.lang = None;
    read.node = node.map(|n| NodeRef {
        datatype: Some(body.datatype),
        ..n
    });
    let before = app.registry.call(&id, &read).await.ok();
    let old = before
        .as_ref()
        .and_then(|a| a.object.value.first().cloned());
    let mut entry = AuditEntry {
        at: cloud_types::now_ms(),
        account: operator.user.clone(),
        lift: id.clone(),
        action: "put".into(),
        object: object.text.clone(),
        old_value: old,
        new_value: body.value.clone(),
        result: PENDING.into(),
        address: Some(client.ip().to_string()),
    };
    // Unknown: as if it needed a privilege, so only the one who elevated may try.
    let needed = before.map_or(Some(1), |a| a.object.privilege).unwrap_or(1);
    if let Err(refused) = may_write(&app, &operator, &id, needed).await {
        entry.result = format!("refused: {}", refused.1.message);
        app.audit.record(&entry).await;
        return Err(refused);
    }
    // Written as intended first: what cannot be audited is not done.
    let audited = app.audit.intent(&entry).await?;
    let params = PutParams {
        sernum,
        lang: None,
        node,
        object: PutObject {
            mplex: object,
            datatype: body.datatype,
            physunit: body.physunit,
            value: body.value,
        },
    };
    let result = app.registry.call(&id, &params).await;
    app.audit.outcome(audited, outcome(&result), None).await;
    Ok(Json(result?))
}

/// Whether `operator` may write an object of `lift` that needs privilege `needed`: above 0
/// only an engineer, and only the one who elevated the lift's connection (docs/PORTAL.md
/// §Users and roles).
async fn may_write(
    app: &AppState,
    operator: &Operator,
    lift: &str,
    needed: u32,
) -> Result<(), ApiError> {
    if needed == 0 {
        return Ok(());
    }
    if !operator.may(Role::Engineer) {
        return Err(error(
            StatusCode::FORBIDDEN,
            format!(
                "this object needs privilege {needed}: writing it needs the role engineer (who elevates first)"
            ),
        ));
    }
    let connection = app.registry.connection(lift);
    app.auth
        .elevations
        .check(
            lift,
            &operator.user,
            needed,
            connection,
            cloud_types::now_ms(),
        )
        .await?
        .map_err(|r| error(StatusCode::FORBIDDEN, r.to_string()))
}

/// `get_canopen_object` on the lift, the object given by name ([`get_object`]).
#[utoipa::path(get, path = "/api/v1/lifts/{id}/objects", operation_id = "getObjectByName",
    tag = "objects", params(LiftPath, NameQuery, GetQuery),
    extensions(("x-least-role" = json!("viewer"))),
    responses((status = 200, description = "the gateway's answer", body = ObjectAnswer),
        (status = 400, description = "no name, an unknown name, or a name several objects start with (the message lists them); or the gateway's refusal with its NXg error", body = ErrorObject),
        NoObject, GatewayAway))]
async fn get_named(
    app: State<Arc<AppState>>,
    caller: Caller,
    Path(LiftPath { id }): Path<LiftPath>,
    ApiQuery(NameQuery { name }): ApiQuery<NameQuery>,
    query: ApiQuery<GetQuery>,
) -> Result<Json<ObjectAnswer>, ApiError> {
    get_object(app, caller, Path(ObjectPath { id, mplex: name }), query).await
}

/// `put_canopen_object` on the lift (audited), the object given by name ([`put_object`]).
#[utoipa::path(put, path = "/api/v1/lifts/{id}/objects", operation_id = "putObjectByName",
    tag = "objects", params(LiftPath, NameQuery),
    request_body(content((PutBody = "application/json", example = json!({"value": "2", "datatype": 7, "physunit": 0})))),
    extensions(("x-least-role" = json!("technician"))),
    responses((status = 200, description = "the gateway's answer", body = PutAnswer),
        (status = 400, description = "no name, an unknown name, or a name several objects start with (the message lists them); or the gateway's refusal of the value with its NXg error", body = ErrorObject),
        WriteRefused, NoObject, GatewayAway))]
async fn put_named(
    app: State<Arc<AppState>>,
    caller: Caller,
    client: ConnectInfo<SocketAddr>,
    Path(LiftPath { id }): Path<LiftPath>,
    ApiQuery(NameQuery { name }): ApiQuery<NameQuery>,
    body: ApiJson<PutBody>,
) -> Result<Json<PutAnswer>, ApiError> {
    put_object(
        app,
        caller,
        client,
        Path(ObjectPath { id, mplex: name }),
        body,
    )
    .await
}

/// What the audit log says about a gateway request's outcome.
fn outcome<T>(result: &Result<T, Failure>) -> String {
    match result {
        Ok(_) => "ok".into(),
        Err(Failure::Error(e)) => format!("error {}", e.code),
        Err(Failure::Invalid(_)) => "invalid answer".into(),
        Err(f) => format!("{f:?}").to_lowercase(),
    }
}

/// `elevate_privilege` with the SHA-1 of the password (NXg §6.4), audited; the grant is the
/// caller's alone, on the gateway's current connection.
#[utoipa::path(post, path = "/api/v1/lifts/{id}/privilege", operation_id = "elevatePrivilege",
    tag = "objects", params(LiftPath),
    request_body(content((PrivilegeBody = "application/json", example = json!({"privilege": 1, "password": "service"})))),
    extensions(("x-least-role" = json!("engineer"))),
    responses((status = 200, description = "the gateway's answer", body = ElevateAnswer),
        (status = 400, description = "the gateway's refusal with its NXg error (a wrong password)", body = ErrorObject),
        NoLift, GatewayAway))]
async fn privilege(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    ConnectInfo(client): ConnectInfo<SocketAddr>,
    Path(LiftPath { id }): Path<LiftPath>,
    ApiJson(body): ApiJson<PrivilegeBody>,
) -> Result<Json<ElevateAnswer>, ApiError> {
    let (operator, id) = lift_of(&app, caller, &id, Role::Engineer).await?;
    let sernum = app.registry.sernum(&id).ok_or(Failure::Gone)?;
    let connection = app.registry.connection(&id).ok_or(Failure::Gone)?;
    // NXg §6.4: the gateway compares the unsalted SHA-1; the password itself is never stored.
    let params = ElevateParams {
        sernum,
        privilege: u32::from(body.privilege),
        passhash: cloud_store::passhash(&body.password),
    };
    let audited = app
        .audit
        .intent(&AuditEntry {
            at: cloud_types::now_ms(),
            account: operator.user.clone(),
            lift: id.clone(),
            action: "elevate".into(),
            object: "privilege".into(),
            old_value: None,
            new_value: body.privilege.to_string(),
            result: PENDING.into(),
            address: Some(client.ip().to_string()),
        })
        .await?;
    let result = app.registry.call(&id, &params).await;
    if let Ok(answer) = &result {
        // The lift is elevated: answered as it is, whatever the database does now (a grant
        // not recorded only means that this user's writes are refused as not elevated).
        if let Err(e) = app
            .auth
            .elevations
            .granted(
                &id,
                &operator.user,
                params.privilege,
                std::time::Duration::from_secs(answer.duration),
                connection,
                cloud_types::now_ms(),
            )
            .await
        {
            tracing::error!(error = %e, lift = %id, "elevation grant not recorded");
        }
    }
    app.audit.outcome(audited, outcome(&result), None).await;
    Ok(Json(result?))
}

/// Forget the lift's cloud token (NXg §5.4): the gateway's next CONNECT is a first contact
/// that gets a new one — for a gateway that was replaced or wiped. Audited; no token is shown.
#[utoipa::path(delete, path = "/api/v1/lifts/{id}/token", operation_id = "resetToken",
    tag = "tokens", params(LiftPath),
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 204, description = "forgotten"), NoLift))]
async fn reset_token(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(LiftPath { id }): Path<LiftPath>,
) -> Result<StatusCode, ApiError> {
    let (operator, id) = lift_of(&app, caller, &id, Role::Admin).await?;
    if app
        .store
        .reset_token(&operator.account.domain, &id, &operator.user)
        .await?
    {
        Ok(StatusCode::NO_CONTENT)
    } else {
        Err(error(StatusCode::NOT_FOUND, "no such lift"))
    }
}

/// Replace the online gateway's cloud token now (`update_unique_token`, NXg §5.4): the new one
/// is recorded as the next token before it is sent, so a lost answer does not lock the gateway
/// out. Audited; the token is never shown.
#[utoipa::path(post, path = "/api/v1/lifts/{id}/token", operation_id = "rotateToken",
    tag = "tokens", params(LiftPath),
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 204, description = "the gateway stored the new token; the portal expects it from now on"),
        (status = 400, description = "the gateway refused the token", body = ErrorObject),
        NoLift, GatewayAway))]
async fn rotate_token(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    ConnectInfo(client): ConnectInfo<SocketAddr>,
    Path(LiftPath { id }): Path<LiftPath>,
) -> Result<StatusCode, ApiError> {
    let (operator, id) = lift_of(&app, caller, &id, Role::Admin).await?;
    let sernum = app.registry.sernum(&id).ok_or(Failure::Gone)?;
    let audited = app
        .audit
        .intent(&AuditEntry {
            at: cloud_types::now_ms(),
            account: operator.user,
            lift: id.clone(),
            action: "token rotated".into(),
            object: "cloud token".into(),
            old_value: None,
            new_value: "(new token)".into(),
            result: PENDING.into(),
            address: Some(client.ip().to_string()),
        })
        .await?;
    let token = cloud_store::secret("");
    if let Err(e) = app.store.set_next_token(&id, &token).await {
        app.audit
            .outcome(audited, "not sent: database".into(), None)
            .await;
        return Err(e.into());
    }
    let params = TokenParams {
        sernum,
        token: token.clone(),
    };
    let result = app.registry.call(&id, &params).await;
    if result.is_ok() {
        // The gateway keeps the new token; were it not recorded as in use, it is still the
        // next one, which its next CONNECT confirms (NXg §5.4).
        if let Err(e) = app
            .store
            .set_token(&id, &operator.account.domain, &token)
            .await
        {
            tracing::error!(error = %e, lift = %id, "new token not recorded as in use: its next CONNECT confirms it");
        }
    }
    app.audit.outcome(audited, outcome(&result), None).await;
    result?;
    Ok(StatusCode::NO_CONTENT)
}

/// The caller holds subscriptions of the objects; the gateway gets the union of what everyone
/// holds on the lift (the smallest inhibit and threshold: docs/PORTAL.md §Subscriptions).
#[utoipa::path(post, path = "/api/v1/lifts/{id}/subscriptions", operation_id = "subscribe",
    tag = "subscriptions", params(LiftPath),
    request_body(content((SubscriptionBody = "application/json", example = json!({"mplex": ["0x652001", "Car speed unit 1"], "inhibit": 500, "threshold": 0.5})))),
    extensions(("x-least-role" = json!("technician"))),
    responses((status = 200, description = "the gateway took them", body = Done),
        (status = 400, description = "an object that is no address or name, a threshold below 0; or the gateway's refusal with its NXg error", body = ErrorObject),
        NoObject, GatewayAway))]
async fn subscribe(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(LiftPath { id }): Path<LiftPath>,
    ApiJson(body): ApiJson<SubscriptionBody>,
) -> Result<Json<Done>, ApiError> {
    let held = Held::of(&app, caller, &id, &body.mplex).await?;
    let terms = terms(body.inhibit, body.threshold)?;
    app.subscriptions
        .subscribe(
            &held.lift,
            &held.subscriber,
            &held.objects,
            terms,
            WhenOffline::Refuse,
        )
        .await?;
    app.store
        .subscribe_objects(
            &held.lift,
            &held.user,
            &held.listed,
            terms.inhibit,
            terms.threshold,
        )
        .await?;
    Ok(Json(Done::OK))
}

/// The caller lets go of its own subscriptions of the objects; an object leaves the gateway
/// when its last holder lets go, one holder's `DELETE` never changes another's pushes.
#[utoipa::path(delete, path = "/api/v1/lifts/{id}/subscriptions", operation_id = "unsubscribe",
    tag = "subscriptions", params(LiftPath),
    request_body(content((UnsubscribeBody = "application/json", example = json!({"mplex": ["0x652001"]})))),
    extensions(("x-least-role" = json!("technician"))),
    responses((status = 200, description = "let go of", body = Done),
        (status = 400, description = "an object that is no address or name; or the gateway's refusal with its NXg error", body = ErrorObject),
        NoObject, GatewayAway))]
async fn unsubscribe(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(LiftPath { id }): Path<LiftPath>,
    ApiJson(body): ApiJson<UnsubscribeBody>,
) -> Result<Json<Done>, ApiError> {
    let held = Held::of(&app, caller, &id, &body.mplex).await?;
    app.store
        .unsubscribe_objects(&held.lift, &held.user, &held.listed)
        .await?;
    app.subscriptions
        .unsubscribe(&held.lift, &held.subscriber, Some(&held.objects))
        .await?;
    Ok(Json(Done::OK))
}

/// What [`subscribe`] and [`unsubscribe`] act on: the caller's lift and the objects it names,
/// recorded for the gateway's next connection, to whichever process (docs/PORTAL.md
/// §Subscriptions): taken once the gateway took them, let go of whatever it answers.
struct Held {
    lift: String,
    user: String,
    subscriber: Subscriber,
    objects: Vec<nxg::mplex::Mplex>,
    /// The objects as the store keeps them.
    listed: Vec<String>,
}

impl Held {
    async fn of(
        app: &AppState,
        caller: Caller,
        id: &str,
        mplex: &[String],
    ) -> Result<Held, ApiError> {
        let (operator, lift) = lift_of(app, caller, id, Role::Technician).await?;
        let objects = objects(&app.names, mplex)?;
        Ok(Held {
            lift,
            subscriber: Subscriber::User(operator.user.clone()),
            user: operator.user,
            listed: objects.iter().map(ToString::to_string).collect(),
            objects,
        })
    }
}

/// The objects of a subscription, each as an mplex or a name.
fn objects(names: &ObjectNames, list: &[String]) -> Result<Vec<nxg::mplex::Mplex>, ApiError> {
    list.iter()
        .map(|m| mplex(names, m).map(|t| t.mplex))
        .collect()
}

/// A subscription's terms: no inhibit and no threshold unless given; a threshold is a number
/// ≥ 0.
fn terms(inhibit: Option<u64>, threshold: Option<f64>) -> Result<Terms, ApiError> {
    let threshold = threshold.unwrap_or(0.0);
    if threshold.is_nan() || threshold < 0.0 {
        return Err(error(StatusCode::BAD_REQUEST, "threshold: a number ≥ 0"));
    }
    Ok(Terms {
        inhibit: inhibit.unwrap_or(0),
        threshold,
    })
}

/// The lift's live events as Server-Sent Events: `value` (notifications), `online` changes,
/// `event` (bus events) and `alarm` (alarm changes). With `?mplex=A,B…` (and `inhibit`,
/// `threshold`) the stream holds subscriptions of those objects for as long as it is open —
/// kept while the gateway is offline and registered when it connects — and lets go of them
/// when it ends; that takes a technician (a viewer's stream holds nothing: 403).
#[utoipa::path(get, path = "/api/v1/lifts/{id}/events", operation_id = "streamEvents",
    tag = "subscriptions", params(LiftPath, EventsQuery),
    extensions(("x-least-role" = json!("viewer"))),
    responses((status = 200, description = "the event stream: value, online, event and alarm events, each with one data line of JSON (ValueMessage, OnlineMessage, BusEventMessage, an alarm)",
            content_type = "text/event-stream", body = crate::sse::SseEvent),
        (status = 400, description = "an object that is no address or name, or a threshold below 0", body = ErrorObject),
        (status = 403, description = "with mplex: holding subscriptions needs the role technician (a viewer may watch without mplex)", body = ErrorObject),
        NoLift,
        (status = 504, description = "the gateway did not answer the registration in time", body = ErrorObject)))]
async fn events(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(LiftPath { id }): Path<LiftPath>,
    ApiQuery(q): ApiQuery<EventsQuery>,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    // Holding subscriptions on the gateway is a technician's (docs/PORTAL.md §Users and
    // roles): a viewer watches what is held already.
    let least = if q.mplex.is_some() {
        Role::Technician
    } else {
        Role::Viewer
    };
    // The terms are checked whether or not objects are named: a stream takes no parameter it
    // would refuse with them.
    let terms = terms(q.inhibit, q.threshold)?;
    let (_, id) = lift_of(&app, caller, &id, least).await?;
    let rx = app.registry.subscribe(&id).await;
    let watching = match q.mplex.as_deref() {
        Some(list) => {
            let list: Vec<String> = list.split(',').map(str::to_owned).collect();
            let objects = objects(&app.names, &list)?;
            let subscriber = app.subscriptions.watcher();
            app.subscriptions
                .subscribe(&id, &subscriber, &objects, terms, WhenOffline::Keep)
                .await?;
            Some(Watching {
                subscriptions: app.subscriptions.clone(),
                lift: id.clone(),
                subscriber,
            })
        }
        None => None,
    };
    let online = cloud_types::live::LiftEvent::Online(app.registry.online(&id));
    let shown = shown_id(&id).to_owned();
    let (kind, data) = online.to_sse(&shown);
    let first = Event::default().event(kind).data(data);
    // The watcher's subscriptions live in the stream's state: dropped with it.
    let state = (rx, Some(first), shown, watching);
    let stream = futures_util::stream::unfold(state, |(mut rx, first, id, watching)| async move {
        if let Some(first) = first {
            return Some((Ok(first), (rx, None, id, watching)));
        }
        loop {
            match rx.recv().await {
                Ok(event) => {
                    let (kind, data) = event.to_sse(&id);
                    let event = Event::default().event(kind).data(data);
                    return Some((Ok(event), (rx, None, id, watching)));
                }
                Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => continue,
                Err(tokio::sync::broadcast::error::RecvError::Closed) => return None,
            }
        }
    });
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}

/// The subscriptions an open event stream holds; let go of when the stream is dropped.
struct Watching {
    subscriptions: Arc<Subscriptions>,
    lift: String,
    subscriber: Subscriber,
}

impl Drop for Watching {
    fn drop(&mut self) {
        let subscriptions = self.subscriptions.clone();
        let lift = std::mem::take(&mut self.lift);
        let subscriber = self.subscriber.clone();
        // Dropping cannot wait for the gateway; the release runs on its own.
        if let Ok(runtime) = tokio::runtime::Handle::try_current() {
            runtime.spawn(async move {
                if let Err(e) = subscriptions.unsubscribe(&lift, &subscriber, None).await {
                    tracing::debug!(%lift, failure = %e, "a watcher's subscriptions not released");
                }
            });
        }
    }
}

/// Stored values of an object over a period, in at most `points` buckets (docs/PORTAL.md
/// §History).
#[utoipa::path(get, path = "/api/v1/lifts/{id}/objects/{mplex}/history",
    operation_id = "getObjectHistory", tag = "history", params(ObjectPath, HistoryQuery),
    extensions(("x-least-role" = json!("viewer"))),
    responses((status = 200, description = "the buckets", body = History),
        (status = 400, description = "not an object address or name, or a time or point count beyond its bounds", body = ErrorObject),
        NoLift))]
async fn history(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(ObjectPath { id, mplex: text }): Path<ObjectPath>,
    ApiQuery(q): ApiQuery<HistoryQuery>,
) -> Result<Json<History>, ApiError> {
    let (_, id) = lift_of(&app, caller, &id, Role::Viewer).await?;
    let m = mplex(&app.names, &text)?.mplex.to_string();
    let times = 0..=cloud_types::LATEST_MS;
    let to = bounded("to", q.to, times.clone())?.unwrap_or_else(cloud_types::now_ms);
    let from = bounded("from", q.from, times)?.unwrap_or(to.saturating_sub(86_400_000));
    let points = bounded("points", q.points, 1..=HISTORY_POINTS_MAX)?.unwrap_or(HISTORY_POINTS);
    let answer = app
        .store
        .history(&id, &m, from, to, points as usize)
        .await?;
    Ok(Json(History {
        lift: shown_id(&id).to_owned(),
        mplex: m,
        from,
        to,
        width: answer.width,
        source: answer.source.name().to_owned(),
        points: answer.buckets.into_iter().map(point_of).collect(),
    }))
}

/// A store's bucket as the API shows it.
pub(crate) fn point_of(b: cloud_store::Bucket) -> HistoryPoint {
    HistoryPoint {
        at: b.at,
        min: b.min,
        max: b.max,
        last: b.last,
        last_at: b.last_at,
        count: b.count,
    }
}

/// Audit log of the account's lifts: who, when, lift, object, old and new value, result.
#[utoipa::path(get, path = "/api/v1/audit", operation_id = "listAudit", tag = "audit",
    extensions(("x-least-role" = json!("viewer"))),
    responses((status = 200, description = "the entries", body = Vec<AuditEntry>)))]
async fn audit(
    State(app): State<Arc<AppState>>,
    caller: Caller,
) -> Result<Json<Vec<AuditEntry>>, ApiError> {
    let operator = allowed(caller, Role::Viewer)?;
    Ok(Json(app.store.audit_log(&operator.account.domain).await?))
}

/// The operations and their routes, from one list: a route is registered with its operation
/// in the document ([`document`]).
fn operations() -> OpenApiRouter<Arc<AppState>> {
    OpenApiRouter::with_openapi(<document::Frame as utoipa::OpenApi>::openapi())
        .routes(routes!(lifts))
        .routes(routes!(retire))
        .routes(routes!(get_named, put_named))
        .routes(routes!(get_object, put_object))
        .routes(routes!(history))
        .routes(routes!(privilege))
        .routes(routes!(rotate_token, reset_token))
        .routes(routes!(subscribe, unsubscribe))
        .routes(routes!(events))
        .routes(routes!(alarms::event_log))
        .routes(routes!(alarms::list))
        .routes(routes!(alarms::acknowledge))
        .routes(routes!(audit))
        .routes(routes!(reports::availability))
        .routes(routes!(reports::monthly))
        .routes(routes!(reports::target))
        .routes(routes!(users::list, users::add))
        .routes(routes!(users::role))
        .routes(routes!(users::disable))
        .routes(routes!(users::reset))
        .routes(routes!(users::keys, users::add_key))
        .routes(routes!(users::revoke))
}

/// The routes and the document of the operations.
fn parts() -> (Router<Arc<AppState>>, utoipa::openapi::OpenApi) {
    let (router, mut document) = operations().split_for_parts();
    utoipa::Modify::modify(&document::Refusals, &mut document);
    (router, document)
}

/// The OpenAPI document of this API, generated from the handlers and the body types
/// (docs/PORTAL.md §Operator REST API).
pub fn document() -> utoipa::openapi::OpenApi {
    parts().1
}

/// The `/api/v1` routes.
pub fn routes(app: Arc<AppState>) -> Router {
    let (router, document) = parts();
    // Made once: every request for it is answered with the same bytes, shared, not copied.
    let document = axum::body::Bytes::from(
        document
            .to_json()
            .unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}")),
    );
    router
        .route(
            "/api/v1/openapi.json",
            get(move || async move {
                (
                    [(axum::http::header::CONTENT_TYPE, "application/json")],
                    document.clone(),
                )
            }),
        )
        .layer(axum::middleware::from_fn_with_state(
            app.clone(),
            idempotency::once,
        ))
        .with_state(app)
}
