//! The alarm and event-log operations of the REST API (docs/PORTAL.md §Alarms): an account
//! sees the alarms and events of its own lifts only (404 for any other); a viewer reads them, a
//! technician also acknowledges.

use std::sync::Arc;

use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::Json;

use super::lift_of;
use crate::alarms::service::AckError;
use crate::auth::{allowed, Caller};
use crate::errors::{error, ApiError, ApiJson, ApiQuery};
use crate::state::AppState;
use cloud_types::alarms::Alarm;
use cloud_types::api::{AckBody, AlarmList, AlarmState, AlarmsQuery, EventLog, EventLogQuery};
use cloud_types::users::Role;
use nxg::msg::ErrorObject;

use cloud_store::AlarmFilter;

/// The most alarms or events one answer lists (the OpenAPI document's `limit` maximum).
const LIMIT_MAX: u32 = 10_000;

/// Alarms of the account's lifts, newest first.
#[utoipa::path(get, path = "/api/v1/alarms", operation_id = "listAlarms", tag = "alarms",
    params(AlarmsQuery), extensions(("x-least-role" = json!("viewer"))),
    responses((status = 200, description = "the alarms", body = AlarmList),
        (status = 400, description = "a limit beyond its bounds, an unknown state", body = ErrorObject)))]
pub(super) async fn list(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    ApiQuery(q): ApiQuery<AlarmsQuery>,
) -> Result<Json<AlarmList>, ApiError> {
    let operator = allowed(caller, Role::Viewer)?;
    let limit = super::bounded("limit", q.limit, 1..=LIMIT_MAX)?.unwrap_or(500);
    let lift = match q.lift {
        Some(id) => match super::key_of(&app, &operator.account, &id).await? {
            Some(key) => Some(key),
            // Not a lift of the account: none of its alarms.
            None => return Ok(Json(AlarmList { alarms: Vec::new() })),
        },
        None => None,
    };
    let filter = AlarmFilter {
        active: q.state.unwrap_or_default() == AlarmState::Active,
        lift,
        limit,
    };
    let alarms = app.store.alarms(&operator.account.domain, &filter).await?;
    Ok(Json(AlarmList {
        alarms: alarms.into_iter().map(shown).collect(),
    }))
}

/// `alarm` as its account sees it: its lift by the id the account knows it by.
pub(crate) fn shown(mut alarm: Alarm) -> Alarm {
    alarm.lift = cloud_types::lifts::shown_id(&alarm.lift).to_owned();
    alarm
}

/// Acknowledge an alarm: who (the caller), when, with a comment. 404 for an alarm of another
/// account, 409 for one taken on before.
#[utoipa::path(post, path = "/api/v1/alarms/{id}/ack", operation_id = "acknowledgeAlarm",
    tag = "alarms",
    params(("id" = i64, Path, description = "the alarm", example = 1)),
    request_body(content((AckBody = "application/json", example = json!({"comment": "technician on the way"})))),
    extensions(("x-least-role" = json!("technician"))),
    responses((status = 200, description = "the alarm, acknowledged", body = Alarm),
        (status = 400, description = "a comment longer than 1000 characters", body = ErrorObject),
        (status = 404, description = "no such alarm in the caller's account", body = ErrorObject),
        (status = 409, description = "acknowledged before (the message says by whom)", body = ErrorObject)))]
pub(super) async fn acknowledge(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(id): Path<String>,
    ApiJson(body): ApiJson<AckBody>,
) -> Result<Json<Alarm>, ApiError> {
    let operator = allowed(caller, Role::Technician)?;
    let Ok(id) = id.parse::<i64>() else {
        return Err(error(StatusCode::NOT_FOUND, "no such alarm"));
    };
    if body.comment.chars().count() > 1000 {
        return Err(error(
            StatusCode::BAD_REQUEST,
            "comment: at most 1000 characters",
        ));
    }
    match app
        .alarms
        .acknowledge(&operator.account.domain, id, &operator.user, &body.comment)
        .await
    {
        Ok(alarm) => Ok(Json(shown(alarm))),
        Err(AckError::NotFound) => Err(error(StatusCode::NOT_FOUND, "no such alarm")),
        Err(AckError::Already(alarm)) => Err(error(
            StatusCode::CONFLICT,
            format!(
                "acknowledged before by {}",
                alarm.acknowledged.map(|a| a.by).unwrap_or_default()
            ),
        )),
        Err(AckError::Store(e)) => Err(e.into()),
    }
}

/// Stored bus events of a lift, oldest first.
#[utoipa::path(get, path = "/api/v1/lifts/{id}/event-log", operation_id = "listBusEvents",
    tag = "alarms", params(super::LiftPath, EventLogQuery),
    extensions(("x-least-role" = json!("viewer"))),
    responses((status = 200, description = "the events", body = EventLog),
        (status = 400, description = "a time that is neither RFC 3339 nor ms since the epoch, a limit beyond its bounds", body = ErrorObject),
        super::document::NoLift))]
pub(super) async fn event_log(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    Path(super::LiftPath { id }): Path<super::LiftPath>,
    ApiQuery(q): ApiQuery<EventLogQuery>,
) -> Result<Json<EventLog>, ApiError> {
    let (_, id) = lift_of(&app, caller, &id, Role::Viewer).await?;
    let since = match q.since.as_deref() {
        None => None,
        Some(text) => Some(
            text.parse::<i64>()
                .ok()
                .or_else(|| nxg::msg::parse_time(text))
                .ok_or_else(|| {
                    error(
                        StatusCode::BAD_REQUEST,
                        "since: RFC 3339 (2026-11-23T10:11:12Z) or ms since the epoch",
                    )
                })?,
        ),
    };
    let bodies = app
        .store
        .event_log(
            &id,
            since,
            super::bounded("limit", q.limit, 1..=LIMIT_MAX)?.unwrap_or(100),
        )
        .await?;
    let events = bodies
        .iter()
        .filter_map(|b| serde_json::from_str(b).ok())
        .collect();
    Ok(Json(EventLog { events }))
}
