//! What live viewers of a lift receive (`GET /api/v1/lifts/{id}/events`, the web UI): the
//! lift's events and the Server-Sent Events they become.

use nxg::msg::{Event, Notification};
use serde::{Deserialize, Serialize};

use crate::alarms::AlarmChange;

/// An event for live viewers of a lift (in a cluster, published by the lift's holder for
/// the other processes: docs/CLUSTER.md §What lives where).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", content = "data", rename_all = "snake_case")]
pub enum LiftEvent {
    /// A pushed value.
    Value(Notification),
    /// The gateway came online or went offline.
    Online(bool),
    /// A bus event (docs/PROTOCOL.md §Events).
    Bus(Event),
    /// An alarm changed.
    Alarm(AlarmChange),
}

impl LiftEvent {
    /// The Server-Sent Event of `lift` (the id its account sees, which an alarm's data is
    /// given too): its name and its JSON data.
    pub fn to_sse(&self, lift: &str) -> (&'static str, String) {
        let lift = lift.to_owned();
        match self {
            LiftEvent::Value(n) => (
                "value",
                serde_json::to_string(&ValueMessage {
                    lift,
                    object: n.clone(),
                })
                .unwrap_or_default(),
            ),
            LiftEvent::Online(online) => (
                "online",
                serde_json::to_string(&OnlineMessage {
                    lift,
                    online: *online,
                })
                .unwrap_or_default(),
            ),
            LiftEvent::Bus(event) => (
                "event",
                serde_json::to_string(&BusEventMessage {
                    lift,
                    event: event.clone(),
                })
                .unwrap_or_default(),
            ),
            LiftEvent::Alarm(change) => {
                let mut change = change.clone();
                change.alarm.lift = lift;
                ("alarm", serde_json::to_string(&change).unwrap_or_default())
            }
        }
    }
}

/// The data of the Server-Sent Event `value`: a pushed value of a lift.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ValueMessage {
    /// Lift id.
    pub lift: String,
    /// The gateway's notification.
    pub object: Notification,
}

/// The data of the Server-Sent Event `online`: the lift's gateway connected or went away.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct OnlineMessage {
    /// Lift id.
    pub lift: String,
    /// Connected now.
    pub online: bool,
}

/// The data of the Server-Sent Event `event`: a bus event of the lift (docs/PROTOCOL.md
/// §Events).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct BusEventMessage {
    /// Lift id.
    pub lift: String,
    /// The event as the gateway pushed it.
    pub event: nxg::msg::Event,
}
