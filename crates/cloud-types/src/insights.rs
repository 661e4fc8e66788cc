//! Lift insights as the API shows them (docs/PORTAL.md §Availability): what a lift was doing
//! from the portal's point of view at every moment ([`Status`]), and the availability and fault
//! figures of a period ([`LiftFigures`], [`AvailabilityReport`], [`MonthlyReport`]).

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

/// What a lift was doing as the portal saw it. Every moment of a period is exactly one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Status {
    /// Its gateway was connected and its state object said it serves passengers.
    InService,
    /// Its gateway was connected and its state object said it does not (a fault, a fast stop).
    OutOfService,
    /// Its gateway was not connected: the portal could not see the lift.
    Offline,
    /// Connected, but no state value had come yet — or nothing was recorded at all.
    Unknown,
}

impl Status {
    /// Every status.
    pub const ALL: [Status; 4] = [
        Status::InService,
        Status::OutOfService,
        Status::Offline,
        Status::Unknown,
    ];

    /// The name in the API and the store.
    pub fn name(self) -> &'static str {
        match self {
            Status::InService => "in-service",
            Status::OutOfService => "out-of-service",
            Status::Offline => "offline",
            Status::Unknown => "unknown",
        }
    }

    /// The status called `name`.
    pub fn from_name(name: &str) -> Option<Status> {
        Status::ALL.into_iter().find(|s| s.name() == name)
    }
}

/// The query of `GET /api/v1/reports/availability`: a period (RFC 3339 or ms since the epoch),
/// optionally one lift, and the answer's form.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::IntoParams))]
#[cfg_attr(feature = "openapi", into_params(parameter_in = Query))]
#[serde(deny_unknown_fields)]
pub struct AvailabilityQuery {
    /// Start of the period (included): RFC 3339 with any offset, or ms since the epoch.
    #[cfg_attr(
        feature = "openapi",
        param(
            pattern = r"^([0-9]{1,15}|[0-9]{4}-(0[1-9]|1[0-2])-(0[1-9]|[12][0-9]|3[01])[Tt]([01][0-9]|2[0-3]):[0-5][0-9]:[0-5][0-9](\.[0-9]{1,9})?([Zz]|[+-]([01][0-9]|2[0-3]):[0-5][0-9]))$",
            example = "2026-03-01T00:00:00Z"
        )
    )]
    pub from: String,
    /// End of the period (excluded): after `from`, at most 400 days later.
    #[cfg_attr(
        feature = "openapi",
        param(
            pattern = r"^([0-9]{1,15}|[0-9]{4}-(0[1-9]|1[0-2])-(0[1-9]|[12][0-9]|3[01])[Tt]([01][0-9]|2[0-3]):[0-5][0-9]:[0-5][0-9](\.[0-9]{1,9})?([Zz]|[+-]([01][0-9]|2[0-3]):[0-5][0-9]))$",
            example = "2026-04-01T00:00:00+02:00"
        )
    )]
    pub to: String,
    /// Only this lift.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(example = "1050-4096-180917010200000102"))]
    pub lift: Option<String>,
    /// `json` (default) or `csv`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(feature = "openapi", param(pattern = "^(json|csv)$"))]
    pub format: Option<String>,
}

/// One lift's figures over a period (docs/PORTAL.md §Availability defines each).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct LiftFigures {
    /// The lift.
    pub lift: String,
    /// `in_service_s / (in_service_s + out_of_service_s)`; none when neither was seen.
    pub availability: Option<f64>,
    /// Seconds in service.
    pub in_service_s: f64,
    /// Seconds out of service.
    pub out_of_service_s: f64,
    /// Seconds its gateway was offline.
    pub offline_s: f64,
    /// Seconds nothing was known.
    pub unknown_s: f64,
    /// Faults the lift reported (EMCY alarms raised in the period).
    pub faults: u64,
    /// Those by EMCY error code (`0xFF01`).
    pub faults_by_kind: BTreeMap<String, u64>,
    /// Trips (the trip counter's increase), when the counter was stored.
    pub trips: Option<u64>,
    /// `faults × 1000 / trips`; none without trips.
    pub faults_per_1000_trips: Option<f64>,
    /// Mean time between failures: `in_service_s` per out-of-service episode that began in
    /// the period; none without one.
    pub mtbf_s: Option<f64>,
    /// Mean time to repair: `out_of_service_s` per out-of-service episode in the period;
    /// none without one.
    pub mttr_s: Option<f64>,
    /// Door cycles (the counter's increase).
    pub door_cycles: Option<u64>,
    /// Reopenings for the light barrier (the counter's increase).
    pub reopenings: Option<u64>,
}

/// `GET /api/v1/reports/availability`: the period and each lift's figures.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct AvailabilityReport {
    /// Start (RFC 3339, UTC).
    pub from: String,
    /// End (RFC 3339, UTC).
    pub to: String,
    /// The lifts, in the order of their ids.
    pub lifts: Vec<LiftFigures>,
}

/// The columns of the CSV form, in order: the fields of [`LiftFigures`] but `faults_by_kind`,
/// which follows as `KIND=N` pairs separated by `;`.
pub const CSV_COLUMNS: [&str; 14] = [
    "lift",
    "availability",
    "in_service_s",
    "out_of_service_s",
    "offline_s",
    "unknown_s",
    "faults",
    "faults_by_kind",
    "trips",
    "faults_per_1000_trips",
    "mtbf_s",
    "mttr_s",
    "door_cycles",
    "reopenings",
];

/// The query of the monthly report: `YYYY-MM`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::IntoParams))]
#[cfg_attr(feature = "openapi", into_params(parameter_in = Query))]
#[serde(deny_unknown_fields)]
pub struct MonthQuery {
    /// The month (UTC), `YYYY-MM`; default: the last complete month.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    #[cfg_attr(
        feature = "openapi",
        param(
            pattern = "^(19[7-9][0-9]|[2-9][0-9]{3})-(0[1-9]|1[0-2])$",
            example = "2026-03"
        )
    )]
    pub month: Option<String>,
}

/// One month of an account's lifts against its availability target.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct MonthlyReport {
    /// The month, `YYYY-MM`.
    pub month: String,
    /// The account.
    pub account: String,
    /// The availability the account promises (0–1).
    pub target: f64,
    /// The account's availability: its lifts' seconds in service over in and out of service.
    pub availability: Option<f64>,
    /// Faults of all lifts by EMCY code.
    pub faults_by_kind: BTreeMap<String, u64>,
    /// The three months before, oldest first: month and availability.
    pub trend: Vec<MonthAvailability>,
    /// The lifts, the least available first (those without a figure last).
    pub lifts: Vec<LiftFigures>,
}

/// A month's availability of an account.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct MonthAvailability {
    /// `YYYY-MM`.
    pub month: String,
    /// The availability (none when nothing was seen).
    pub availability: Option<f64>,
}
