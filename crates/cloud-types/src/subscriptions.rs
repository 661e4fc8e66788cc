//! Who holds subscriptions of a lift's objects, and on what terms (docs/PORTAL.md
//! §Subscriptions): the types the portal's processes, its store and its API share.

use serde::{Deserialize, Serialize};

/// Who holds a subscription (docs/PORTAL.md §Subscriptions).
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Subscriber {
    /// A user (or an account's own key), through `POST /api/v1/lifts/{id}/subscriptions`
    /// (until its `DELETE`).
    User(String),
    /// One live event stream that asked for objects (until the stream ends). The upper 32
    /// bits are its process's, drawn at random when it starts: unique across a cluster.
    Watcher(u64),
}

impl Subscriber {
    /// The process of a live watcher (the upper 32 bits of its id); `None` for a user.
    pub fn process(&self) -> Option<u64> {
        match self {
            Subscriber::Watcher(id) => Some(id & !u64::from(u32::MAX)),
            Subscriber::User(_) => None,
        }
    }
}

/// What is asked of the pushes of one object.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Terms {
    /// Minimum gap between two pushes (ms).
    pub inhibit: u64,
    /// Smallest change of a number that is pushed.
    pub threshold: f64,
}

impl Terms {
    /// Pushes that satisfy both: the smaller inhibit and the smaller threshold.
    pub fn union(self, other: Terms) -> Terms {
        Terms {
            inhibit: self.inhibit.min(other.inhibit),
            threshold: self.threshold.min(other.threshold),
        }
    }
}
