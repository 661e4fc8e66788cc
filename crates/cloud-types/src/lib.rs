//! What the portal's parts and its clients say to each other: the operator REST API's bodies
//! ([`api`]), the live events of a lift ([`live`]), alarms ([`alarms`]), lifts as the registry
//! knows them ([`lifts`]), accounts, users and roles ([`users`]), the audit log ([`audit`]),
//! who holds which subscriptions ([`subscriptions`]) and lift insights ([`insights`]). Types
//! only — no database, no runtime — so that the store, the cluster, the server and the command-line client build on one
//! vocabulary without depending on each other.

#![warn(missing_docs)]

pub mod alarms;
pub mod api;
pub mod audit;
pub mod insights;
pub mod lifts;
pub mod live;
pub mod subscriptions;
pub mod users;

/// The latest time the API takes (ms since the epoch): the end of the year 9999, as far as RFC
/// 3339 writes years; the earliest is the epoch itself.
pub const LATEST_MS: i64 = 253_402_300_799_999;

/// Milliseconds since the Unix epoch: how the portal stamps what it stores.
pub fn now_ms() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as i64)
}
