//! Lifts as the registry knows them.

use nxg::msg::Identity;

/// The id of a lift in the API: `VENDORID-PRODUCTCODE-SERNUM`.
pub fn lift_id(identity: &Identity) -> String {
    format!(
        "{}-{}-{}",
        identity.vendorid, identity.productcode, identity.sernum
    )
}

/// A lift as the registry knows it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct LiftRecord {
    /// `VENDORID-PRODUCTCODE-SERNUM`.
    pub id: String,
    /// Vendor-ID.
    pub vendorid: u32,
    /// Product code.
    pub productcode: u32,
    /// Serial number.
    pub sernum: String,
    /// The owner's lift number.
    pub liftnum: String,
    /// Hardware.
    pub hardware: String,
    /// Software.
    pub software: String,
    /// Domain token.
    pub domain: String,
    /// API version of the last connection.
    pub api: u32,
    /// Last time the gateway was heard (ms since the epoch).
    pub last_seen: i64,
}
