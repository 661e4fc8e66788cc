//! Who acts on the portal (docs/PORTAL.md §Users and roles): accounts, their users with a
//! role, and API keys as listed.

/// An account: who may see the lifts of one domain.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
pub struct Account {
    /// Name.
    pub name: String,
    /// The domain token its gateways send.
    pub domain: String,
}

/// What a user may do, each role including the ones before it.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, serde::Serialize, serde::Deserialize,
)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Reads objects, live values, events, alarms, history and the audit log.
    Viewer,
    /// Also puts privilege-0 objects (a passenger call), acknowledges alarms, holds
    /// subscriptions.
    Technician,
    /// Also elevates privileges on a lift and puts objects above privilege 0.
    Engineer,
    /// Also manages the account's users, keys and gateway tokens.
    Admin,
}

impl Role {
    /// Every role, from the least to the most.
    pub const ALL: [Role; 4] = [Role::Viewer, Role::Technician, Role::Engineer, Role::Admin];

    /// The name in the CLI, the API and the store.
    pub fn name(self) -> &'static str {
        match self {
            Role::Viewer => "viewer",
            Role::Technician => "technician",
            Role::Engineer => "engineer",
            Role::Admin => "admin",
        }
    }

    /// The role called `name`.
    pub fn from_name(name: &str) -> Option<Role> {
        Role::ALL.into_iter().find(|r| r.name() == name)
    }
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Role {
    type Err = String;

    fn from_str(s: &str) -> Result<Role, String> {
        Role::from_name(s)
            .ok_or_else(|| format!("{s:?} is no role (viewer, technician, engineer, admin)"))
    }
}

/// Who is asking: a user of an account with its role.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Operator {
    /// The account (its lifts are the domain's).
    pub account: Account,
    /// The user (the account's name for the account's own key).
    pub user: String,
    /// What the user may do.
    pub role: Role,
}

impl Operator {
    /// Whether the operator's role includes `role`.
    pub fn may(&self, role: Role) -> bool {
        self.role >= role
    }
}

/// A user as listed.
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct User {
    /// Name (unique on the portal).
    pub name: String,
    /// Its account.
    pub account: String,
    /// Its role.
    pub role: Role,
    /// Whether it was disabled.
    pub disabled: bool,
}

/// An API key as listed (the key itself is shown only when it is made).
#[derive(Debug, Clone, PartialEq, Eq, serde::Serialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct KeyInfo {
    /// Its id (for `key revoke`).
    pub id: String,
    /// The user it acts for.
    pub user: String,
    /// When it stops working (ms since the epoch), if ever.
    pub expires: Option<i64>,
    /// Whether it was revoked.
    pub revoked: bool,
}
