//! The audit log's entries: every write to a lift, elevation and token operation, who did it
//! and how it ended (docs/PORTAL.md §Audit).

/// The audit's "who" for what the portal does by itself (a board change it saw).
pub const BY_PORTAL: &str = "(portal)";
/// The audit's "who" for what an administrator did with `canlift cloud` on the portal's
/// configuration (a token reset).
pub const BY_ADMINISTRATOR: &str = "(administrator)";

/// The result of an entry written as intended, before the lift was asked: it stays so only if
/// the portal stopped before the lift answered (docs/PORTAL.md §Audit).
pub const PENDING: &str = "pending";

/// One audit entry.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct AuditEntry {
    /// When (ms since the epoch).
    pub at: i64,
    /// Account name.
    pub account: String,
    /// Lift id.
    pub lift: String,
    /// `put` or `elevate`.
    pub action: String,
    /// The mplex or the privilege.
    pub object: String,
    /// Value before (puts, when it could be read).
    pub old_value: Option<String>,
    /// Value written, or privilege asked for.
    pub new_value: String,
    /// `ok`, the error, or [`PENDING`] while the lift has not answered.
    pub result: String,
    /// The address the request came from (the client's, behind a trusted load balancer:
    /// docs/PORTAL.md §Behind a load balancer); absent for what the portal or an administrator
    /// on its machine did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub address: Option<String>,
}
