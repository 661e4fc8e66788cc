//! Lifts as the registry knows them.

use nxg::msg::Identity;

/// The id of a lift in the API: `VENDORID-PRODUCTCODE-SERNUM`, unique within its account.
pub fn lift_id(identity: &Identity) -> String {
    format!(
        "{}-{}-{}",
        identity.vendorid, identity.productcode, identity.sernum
    )
}

/// What separates a lift's id from its account's name in a scoped key ([`scoped_key`]): a
/// control character, which no identity the portal admits contains (docs/PROTOCOL.md
/// §Connection), so [`shown_id`] never cuts an id short.
const SCOPE: char = '\u{1f}';

/// The registry's key of lift `id` of `account` when another account's lift already has the key
/// `id` (docs/PORTAL.md §Lifts and accounts). Lifts belong to accounts: a gateway that arrives
/// with the identity of another account's lift and its own account's domain token is a lift
/// of its own account, keyed apart, and changes nothing of the first. The first lift of an
/// identity keeps the plain id as its key, so a registry from before lifts were scoped needs
/// no migration.
pub fn scoped_key(id: &str, account: &str) -> String {
    format!("{id}{SCOPE}{account}")
}

/// The keys lift `id` of `account` may have: the plain id, or the scoped one.
pub fn keys_of(id: &str, account: &str) -> [String; 2] {
    [id.to_owned(), scoped_key(id, account)]
}

/// The id a lift's key shows to its account's operators (the key without its scope).
pub fn shown_id(key: &str) -> &str {
    key.split(SCOPE).next().unwrap_or(key)
}

/// A lift as the registry knows it.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct LiftRecord {
    /// The registry's key ([`shown_id`] is what the account sees: `VENDORID-PRODUCTCODE-SERNUM`).
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
    /// Domain token: it admits gateways into the account, so the API does not show it.
    #[serde(skip_serializing, default)]
    pub domain: String,
    /// API version of the last connection.
    pub api: u32,
    /// Last time the gateway was heard (ms since the epoch).
    pub last_seen: i64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scoped_key_shows_its_id() {
        assert_eq!(shown_id("1050-4096-7"), "1050-4096-7");
        let key = scoped_key("1050-4096-A B/7", "demo");
        assert_ne!(key, "1050-4096-A B/7");
        assert_eq!(shown_id(&key), "1050-4096-A B/7");
        assert_eq!(
            keys_of("x", "demo"),
            ["x".to_owned(), scoped_key("x", "demo")]
        );
    }
}
