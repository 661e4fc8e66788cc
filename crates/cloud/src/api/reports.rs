//! The reports of the REST API (docs/PORTAL.md §Availability, §Monthly report): availability
//! and fault figures of the caller's lifts over any period, as JSON or CSV; an account's month;
//! the availability target the account promises.

use std::sync::Arc;

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;

use crate::auth::{allowed, Caller};
use crate::errors::{error, ApiError, ApiJson, ApiQuery};
use crate::insights::{self, Month};
use crate::state::AppState;
use cloud_store::Lifts;
use cloud_types::insights::{AvailabilityQuery, AvailabilityReport, MonthQuery, MonthlyReport};
use cloud_types::users::Role;
use nxg::msg::ErrorObject;

/// The longest period one report covers (ms): 400 days, as far as the status changes are kept
/// by default.
pub const PERIOD_MAX_MS: i64 = 400 * 86_400_000;

/// A time of the query: RFC 3339 (with any offset) or ms since the epoch.
fn instant(what: &str, text: &str) -> Result<i64, ApiError> {
    // 1–15 digits, as documented: `+5` is no time, though Rust's integers take it.
    let at = if (1..=15).contains(&text.len()) && text.bytes().all(|b| b.is_ascii_digit()) {
        text.parse::<i64>().ok()
    } else {
        nxg::msg::parse_time(text)
    };
    at.filter(|at| (0..=cloud_types::LATEST_MS).contains(at))
        .ok_or_else(|| {
            error(
                StatusCode::BAD_REQUEST,
                format!("{what}: RFC 3339 or ms since the epoch, 1970 to 9999"),
            )
        })
}

/// Availability and fault figures of the account's lifts over a period, as JSON or CSV
/// (docs/PORTAL.md §Availability).
#[utoipa::path(get, path = "/api/v1/reports/availability", operation_id = "availabilityReport",
    tag = "reports", params(AvailabilityQuery), extensions(("x-least-role" = json!("viewer"))),
    responses((status = 200, description = "the figures; with format=csv one line per lift, a header line first (faults_by_kind as CODE=N pairs joined by ;)",
            content((AvailabilityReport = "application/json"), (String = "text/csv"))),
        (status = 400, description = "a time that is neither, an end not after the start or more than 400 days after it, an unknown format", body = ErrorObject),
        (status = 404, description = "no such lift in the caller's account", body = ErrorObject)))]
pub(super) async fn availability(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    ApiQuery(q): ApiQuery<AvailabilityQuery>,
) -> Result<Response, ApiError> {
    let operator = allowed(caller, Role::Viewer)?;
    let (from, to) = (instant("from", &q.from)?, instant("to", &q.to)?);
    if to <= from || to - from > PERIOD_MAX_MS {
        return Err(error(
            StatusCode::BAD_REQUEST,
            "to: after from, at most 400 days later",
        ));
    }
    let csv = match q.format.as_deref() {
        None | Some("json") => false,
        Some("csv") => true,
        Some(_) => return Err(error(StatusCode::BAD_REQUEST, "format: json or csv")),
    };
    let key = match &q.lift {
        Some(id) => Some(
            super::key_of(&app, &operator.account, id)
                .await?
                .ok_or_else(|| error(StatusCode::NOT_FOUND, "no such lift"))?,
        ),
        None => None,
    };
    let lifts = Lifts {
        domain: &operator.account.domain,
        lift: key.as_deref(),
    };
    let figures = insights::figures(&app.store, &app.insights, lifts, from, to).await?;
    if csv {
        return Ok((
            [
                (
                    header::CONTENT_TYPE,
                    "text/csv; charset=utf-8; header=present",
                ),
                (
                    header::CONTENT_DISPOSITION,
                    "attachment; filename=\"availability.csv\"",
                ),
            ],
            insights::csv(&figures),
        )
            .into_response());
    }
    Ok(Json(AvailabilityReport {
        from: nxg::msg::format_time(from),
        to: nxg::msg::format_time(to),
        lifts: figures,
    })
    .into_response())
}

/// The account's month: availability against its target, faults by kind, the three months
/// before, the lifts least available first (docs/PORTAL.md §Monthly report).
#[utoipa::path(get, path = "/api/v1/reports/monthly", operation_id = "monthlyReport",
    tag = "reports", params(MonthQuery), extensions(("x-least-role" = json!("viewer"))),
    responses((status = 200, description = "the report", body = MonthlyReport),
        (status = 400, description = "not a month", body = ErrorObject)))]
pub(super) async fn monthly(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    ApiQuery(q): ApiQuery<MonthQuery>,
) -> Result<Json<MonthlyReport>, ApiError> {
    let operator = allowed(caller, Role::Viewer)?;
    let month = Month::asked(q.month.as_deref())
        .ok_or_else(|| error(StatusCode::BAD_REQUEST, "month: YYYY-MM, 1970 to 9999"))?;
    Ok(Json(
        insights::monthly(&app.store, &app.insights, &operator.account, month).await?,
    ))
}

/// The body of `PUT /api/v1/reports/target` and its answer.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize, utoipa::ToSchema)]
#[serde(deny_unknown_fields)]
#[schema(as = Target)]
pub struct TargetBody {
    /// The availability promised (0–1); null: the portal's default ([insights] target).
    /// Required: absent is not null (the outer `None`).
    #[serde(default, deserialize_with = "present")]
    #[schema(value_type = Option<f64>, required = true, minimum = 0, maximum = 1)]
    pub target: Option<Option<f64>>,
}

/// A field that is there, null or not.
fn present<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Option<Option<f64>>, D::Error> {
    serde::Deserialize::deserialize(d).map(Some)
}

/// Set the availability the account promises (the monthly report's target).
#[utoipa::path(put, path = "/api/v1/reports/target", operation_id = "setAvailabilityTarget",
    tag = "reports",
    request_body(content((TargetBody = "application/json", example = json!({"target": 0.995})))),
    extensions(("x-least-role" = json!("admin"))),
    responses((status = 200, description = "the target in force", body = TargetBody),
        (status = 400, description = "a target outside 0–1", body = ErrorObject)))]
pub(super) async fn target(
    State(app): State<Arc<AppState>>,
    caller: Caller,
    ApiJson(body): ApiJson<TargetBody>,
) -> Result<Json<TargetBody>, ApiError> {
    let operator = allowed(caller, Role::Admin)?;
    let Some(target) = body.target else {
        return Err(error(
            StatusCode::UNPROCESSABLE_ENTITY,
            "target: required (null for the default)",
        ));
    };
    if target.is_some_and(|t| !(0.0..=1.0).contains(&t)) {
        return Err(error(StatusCode::BAD_REQUEST, "target: 0 to 1"));
    }
    app.store
        .set_availability_target(&operator.account.name, target)
        .await?;
    let target = app
        .store
        .availability_target(&operator.account.name)
        .await?
        .unwrap_or(app.insights.target);
    Ok(Json(TargetBody {
        target: Some(Some(target)),
    }))
}
