//! Alarms as the API, the web UI, webhooks and the live stream show them (docs/PORTAL.md
//! §Alarms): fault conditions with a lifecycle — raised → acknowledged (by whom, when, with what
//! comment) → cleared (the condition is gone).

use std::fmt;

use serde::{Deserialize, Serialize};

/// What kind of condition an alarm is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "kebab-case")]
pub enum Kind {
    /// A node reported an error by EMCY.
    Emcy,
    /// A supervised node's heartbeat stayed away.
    NodeOffline,
    /// A network is error-passive, bus-off or unreachable.
    Bus,
    /// The lift's gateway has been offline for `offline_after_s`.
    LiftOffline,
    /// The lift's gateway connected with its valid token from another board (`boardhash`);
    /// it stays until someone acknowledges it (nothing on the lift ends it).
    BoardChanged,
    /// The lift pushed more than it may store per hour (`[gateways]
    /// max_stored_bytes_per_hour`): values are not stored; cleared after an hour within it.
    StorageQuota,
    /// A stored numeric object's recent mean rose above its baseline by more than a trend
    /// rule allows (`[[insights.trends]]`): wear that shows before it fails; cleared when the
    /// mean falls back. Its code is the object's mplex.
    Trend,
}

impl Kind {
    /// The name in the API and the store.
    pub fn name(self) -> &'static str {
        match self {
            Kind::Emcy => "emcy",
            Kind::NodeOffline => "node-offline",
            Kind::Bus => "bus",
            Kind::LiftOffline => "lift-offline",
            Kind::BoardChanged => "board-changed",
            Kind::StorageQuota => "storage-quota",
            Kind::Trend => "trend",
        }
    }

    /// Whether it concerns the lift as a whole rather than a node or network.
    pub fn is_lift_wide(self) -> bool {
        matches!(
            self,
            Kind::LiftOffline | Kind::BoardChanged | Kind::StorageQuota | Kind::Trend
        )
    }

    /// Whether acknowledging it also clears it: nothing the lift reports ends it, a person
    /// confirming it does.
    pub fn cleared_by_acknowledgement(self) -> bool {
        self == Kind::BoardChanged
    }

    /// The kind called `name`.
    pub fn from_name(name: &str) -> Option<Kind> {
        [
            Kind::Emcy,
            Kind::NodeOffline,
            Kind::Bus,
            Kind::LiftOffline,
            Kind::BoardChanged,
            Kind::StorageQuota,
            Kind::Trend,
        ]
        .into_iter()
        .find(|k| k.name() == name)
    }
}

/// How urgent an alarm is; ordered from the least to the most.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "lowercase")]
pub enum Severity {
    /// Worth knowing.
    Minor,
    /// Someone should look today.
    Major,
    /// The lift is out of service or out of reach.
    Critical,
}

impl Severity {
    /// The name in the API and the store.
    pub fn name(self) -> &'static str {
        match self {
            Severity::Minor => "minor",
            Severity::Major => "major",
            Severity::Critical => "critical",
        }
    }

    /// The severity called `name`.
    pub fn from_name(name: &str) -> Option<Severity> {
        [Severity::Minor, Severity::Major, Severity::Critical]
            .into_iter()
            .find(|s| s.name() == name)
    }
}

impl fmt::Display for Severity {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Where on the lift's networks an alarm is: a node, or a whole network (`id` absent).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Place {
    /// Node-ID; absent for a network's alarm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub id: Option<u8>,
    /// Network.
    pub net: u8,
}

/// What makes two alarms the same condition: at most one of each is active at a time.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Condition {
    /// The lift.
    pub lift: String,
    /// The kind.
    pub kind: Kind,
    /// The node or network (none for `lift-offline` and `board-changed`).
    pub place: Option<Place>,
    /// The EMCY code (`0xFF01`) or the network's state (`bus-off`); empty otherwise.
    pub code: String,
}

/// An acknowledgement.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Acknowledgement {
    /// Who acknowledged (the account or user).
    pub by: String,
    /// When (RFC 3339).
    pub at: String,
    /// What they said.
    pub comment: String,
}

/// One alarm as the API shows it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct Alarm {
    /// Its id.
    pub id: i64,
    /// The lift.
    pub lift: String,
    /// The node or network, if the alarm is about one.
    pub node: Option<Place>,
    /// The kind.
    pub kind: Kind,
    /// The EMCY code or the network's state (empty for the other kinds).
    pub code: String,
    /// How urgent.
    pub severity: Severity,
    /// What it is, for people.
    pub text: String,
    /// When it was raised (RFC 3339).
    pub raised: String,
    /// Who acknowledged it, if anyone did.
    pub acknowledged: Option<Acknowledgement>,
    /// When the condition went away, if it did (RFC 3339).
    pub cleared: Option<String>,
}

impl Alarm {
    /// A new alarm `id` for `condition`, raised at `at` (ms).
    pub fn raised(
        id: i64,
        condition: &Condition,
        severity: Severity,
        text: &str,
        at: i64,
    ) -> Alarm {
        Alarm {
            id,
            lift: condition.lift.clone(),
            node: condition.place,
            kind: condition.kind,
            code: condition.code.clone(),
            severity,
            text: text.to_owned(),
            raised: nxg::msg::format_time(at),
            acknowledged: None,
            cleared: None,
        }
    }

    /// Whether the condition still holds.
    pub fn active(&self) -> bool {
        self.cleared.is_none()
    }
}

/// What happened to an alarm (webhooks and the live stream say which).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Change {
    /// The condition began.
    Raised,
    /// Someone took it on.
    Acknowledged,
    /// The condition went away.
    Cleared,
}

impl Change {
    /// The name in the API.
    pub fn name(self) -> &'static str {
        match self {
            Change::Raised => "raised",
            Change::Acknowledged => "acknowledged",
            Change::Cleared => "cleared",
        }
    }
}

/// An alarm change as the live stream shows it.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct AlarmChange {
    /// What happened.
    pub change: Change,
    /// The alarm after the change.
    pub alarm: Alarm,
}

/// An alarm change as a webhook receives it (docs/PORTAL.md §Webhooks): the change, its lift
/// named by the id its account knows it by, and that account (a receiver serves the portal,
/// and lifts of two accounts may have one id).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct WebhookBody {
    /// The change.
    #[serde(flatten)]
    pub change: AlarmChange,
    /// The account of the alarm's lift.
    pub account: String,
}
