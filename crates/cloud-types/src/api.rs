//! The operator REST API's bodies as types (docs/PORTAL.md §Operator REST API): what the
//! portal's handlers read and write and what its client and `canlift lifts|get|put|watch` read
//! back. With the feature `openapi` they are OpenAPI schemas and parameters too, with the bounds
//! the handlers enforce: the portal's `openapi.json` is generated from them. Objects travel in the connector's own types
//! ([`nxg::msg::ObjectAnswer`], [`nxg::msg::Notification`]); errors as
//! [`nxg::msg::ErrorObject`].

use nxg::msg::{GetObject, GetParams, Lang, MplexText};
use serde::{Deserialize, Serialize};

use crate::lifts::LiftRecord;

/// One lift of `GET /api/v1/lifts`: the registry's record and whether its gateway is connected.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct LiftSummary {
    /// What the registry knows.
    #[serde(flatten)]
    pub record: LiftRecord,
    /// The gateway is connected now.
    pub online: bool,
}

/// The query of `GET /api/v1/lifts/{id}/objects/{mplex}`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::IntoParams))]
#[cfg_attr(feature = "openapi", into_params(parameter_in = Query))]
pub struct GetQuery {
    /// Language of names and hints (default `en`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(example = "de"))]
    pub lang: Option<String>,
    /// Second language (default `en`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(example = "en"))]
    pub alt_lang: Option<String>,
    /// `full` (default), `stripped` or `naked`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(inline))]
    pub form: Option<Form>,
    /// Every element of an array (mplex with sub-index 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub compact: Option<bool>,
    /// Another node than the lift controller.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(minimum = 1, maximum = 127))]
    pub node: Option<u8>,
    /// Its network (default 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(minimum = 1, maximum = 255))]
    pub net: Option<u8>,
    /// Its data type, for nodes the gateway has no description of.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(maximum = 4_294_967_295_u32, format = Int64))]
    pub datatype: Option<u32>,
}

/// The object's name in `GET` and `PUT /api/v1/lifts/{id}/objects?name=…` (docs/PROTOCOL.md
/// §Mplex).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::IntoParams))]
#[cfg_attr(feature = "openapi", into_params(parameter_in = Query))]
pub struct NameQuery {
    /// The object's name from the CiA 417 catalog (case-insensitive, English or German, a unique
    /// prefix is enough).
    #[cfg_attr(feature = "openapi", param(example = "Trip counter"))]
    pub name: String,
}

/// How much of an object a read returns (NXg §6.1.1–§6.1.3).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "lowercase")]
pub enum Form {
    /// Everything, names and hints in the asked language.
    #[default]
    Full,
    /// Without names, hints and lists.
    Stripped,
    /// Only the value.
    Naked,
}

impl Form {
    /// The `get_canopen_object` parameters (NXg §6.1) that read `mplex` in this form, names
    /// and hints in `lang`.
    pub fn get(self, mplex: MplexText, lang: Lang) -> GetParams {
        GetParams {
            lang: Some(lang),
            node: None,
            object: GetObject {
                mplex,
                compact: false,
                stripped: self == Form::Stripped,
                naked: self == Form::Naked,
            },
        }
    }
}

/// The body of `PUT /api/v1/lifts/{id}/objects/{mplex}`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct PutBody {
    /// The value in the connector's text form.
    pub value: String,
    /// The data type the caller assumes (NXg §6.3).
    #[cfg_attr(feature = "openapi", schema(maximum = 4_294_967_295_u32, format = Int64))]
    pub datatype: u32,
    /// The physical unit the caller assumes.
    #[cfg_attr(feature = "openapi", schema(maximum = 4_294_967_295_u32, format = Int64))]
    pub physunit: u32,
    /// Another node than the lift controller.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(minimum = 1, maximum = 127))]
    pub node: Option<u8>,
    /// Its network (default 1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(minimum = 1, maximum = 255))]
    pub net: Option<u8>,
}

/// The body of `POST /api/v1/lifts/{id}/privilege`.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct PrivilegeBody {
    /// 1 service, 2 setup (0: back to none).
    #[cfg_attr(feature = "openapi", schema(maximum = 2))]
    pub privilege: u8,
    /// The lift's password for it (sent to the gateway only as its SHA-1, NXg §6.4).
    pub password: String,
}

/// The body of `POST /api/v1/lifts/{id}/subscriptions`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct SubscriptionBody {
    /// The objects (mplex or name).
    pub mplex: Vec<String>,
    /// Minimum gap between two pushes of one object (ms).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(maximum = 18_446_744_073_709_551_615_u64))]
    pub inhibit: Option<u64>,
    /// Smallest change of a number that is pushed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", schema(minimum = 0))]
    pub threshold: Option<f64>,
}

/// The body of `DELETE /api/v1/lifts/{id}/subscriptions`: the objects alone. Letting go has no
/// terms; a client that sends its subscribe body again has its `inhibit` and `threshold`
/// ignored, not judged against a schema that would promise to refuse them.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct UnsubscribeBody {
    /// The objects (mplex or name).
    pub mplex: Vec<String>,
}

/// The query of `GET …/lifts/{id}/events`: objects the stream holds subscriptions of while it
/// is open, with their terms.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::IntoParams))]
#[cfg_attr(feature = "openapi", into_params(parameter_in = Query))]
pub struct EventsQuery {
    /// Objects, comma-separated (mplex or name).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(example = "0x652001,Trip counter"))]
    pub mplex: Option<String>,
    /// Minimum gap between two pushes of one object (ms).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(maximum = 18_446_744_073_709_551_615_u64))]
    pub inhibit: Option<u64>,
    /// Smallest change of a number that is pushed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(minimum = 0))]
    pub threshold: Option<f64>,
}

/// The query of `GET …/objects/{mplex}/history` (ms since the epoch).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::IntoParams))]
#[cfg_attr(feature = "openapi", into_params(parameter_in = Query))]
pub struct HistoryQuery {
    /// From (default: a day before `to`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(
        feature = "openapi",
        param(minimum = 0, maximum = 253_402_300_799_999_i64)
    )]
    pub from: Option<i64>,
    /// To (default: now).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(
        feature = "openapi",
        param(minimum = 0, maximum = 253_402_300_799_999_i64)
    )]
    pub to: Option<i64>,
    /// Buckets at most (default 1000, at most 10,000).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(minimum = 1, maximum = 10000))]
    pub points: Option<u32>,
}

/// Buckets of a history answer unless the query says otherwise.
pub const HISTORY_POINTS: u32 = 1000;

/// Buckets of a history answer at most.
pub const HISTORY_POINTS_MAX: u32 = 10_000;

/// An object's values over one bucket of a history answer.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct HistoryPoint {
    /// The bucket's start (ms since the epoch).
    pub at: i64,
    /// The smallest value that is a number (absent when none is).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min: Option<f64>,
    /// The largest.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max: Option<f64>,
    /// The last value in text form.
    pub last: String,
    /// When the last value came.
    pub last_at: i64,
    /// How many values came.
    pub count: i64,
}

/// The answer of `GET …/objects/{mplex}/history`: the period in at most `points` buckets of
/// equal length spanning all of it, the empty ones left out (docs/PORTAL.md §History).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct History {
    /// Lift id.
    pub lift: String,
    /// The object (the gateway's spelling).
    pub mplex: String,
    /// The period's start (ms since the epoch).
    pub from: i64,
    /// Its end.
    pub to: i64,
    /// The length of a bucket (ms).
    pub width: i64,
    /// What the buckets were made from: `raw` (every value), `minute` or `hour` (the
    /// roll-ups, raw values at the edges).
    pub source: String,
    /// The buckets holding values, oldest first.
    pub points: Vec<HistoryPoint>,
}

/// Which alarms `GET /api/v1/alarms` lists.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "lowercase")]
pub enum AlarmState {
    /// Those whose condition still holds (the default).
    #[default]
    Active,
    /// All, newest first.
    All,
}

/// The query of `GET /api/v1/alarms`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::IntoParams))]
#[cfg_attr(feature = "openapi", into_params(parameter_in = Query))]
#[serde(deny_unknown_fields)]
pub struct AlarmsQuery {
    /// `active` (default) or `all`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(inline))]
    pub state: Option<AlarmState>,
    /// One lift's only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lift: Option<String>,
    /// At most this many (default 500, at most 10,000).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(minimum = 1, maximum = 10000))]
    pub limit: Option<u32>,
}

/// The answer of `GET /api/v1/alarms`, newest first.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct AlarmList {
    /// The alarms.
    pub alarms: Vec<crate::alarms::Alarm>,
}

/// The body of `POST /api/v1/alarms/{id}/ack`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(deny_unknown_fields)]
pub struct AckBody {
    /// What the person taking the alarm on says (may be empty).
    #[serde(default)]
    #[cfg_attr(feature = "openapi", schema(max_length = 1000))]
    pub comment: String,
}

/// The query of `GET /api/v1/lifts/{id}/event-log`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::IntoParams))]
#[cfg_attr(feature = "openapi", into_params(parameter_in = Query))]
#[serde(deny_unknown_fields)]
pub struct EventLogQuery {
    /// From this time on: RFC 3339 with any offset (2026-11-23T10:11:12Z,
    /// 2026-11-23T11:11:12+01:00) or ms since the epoch; absent: the newest. 29 February of a
    /// year without one is refused (400).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(
        feature = "openapi",
        param(
            pattern = r"^([0-9]{1,15}|[0-9]{4}-(((0[13578]|1[02])-(0[1-9]|[12][0-9]|3[01]))|((0[469]|11)-(0[1-9]|[12][0-9]|30))|(02-(0[1-9]|1[0-9]|2[0-9])))T([01][0-9]|2[0-3]):[0-5][0-9]:[0-5][0-9](\.[0-9]{1,9})?(Z|[+-]([01][0-9]|2[0-3]):[0-5][0-9]))$",
            example = "2026-11-23T10:11:12Z"
        )
    )]
    pub since: Option<String>,
    /// At most this many (default 100, at most 10,000).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(minimum = 1, maximum = 10000))]
    pub limit: Option<u32>,
}

/// The answer of `GET /api/v1/lifts/{id}/event-log`, oldest first.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct EventLog {
    /// The events as the gateway pushed them.
    pub events: Vec<nxg::msg::Event>,
}
