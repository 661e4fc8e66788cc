//! Bus events: canlift's extension of the connector (docs/PROTOCOL.md §Events), called by name
//! at any NXg api. A portal registers with `reg_canopen_event`; the gateway then pushes
//! `canopen_event` notifications — EMCY messages of any node, NMT states of the nodes it
//! supervises, and the state of each CAN network — with the payload under `result`, like
//! `canopen_object`.

use std::fmt;

use serde::{Deserialize, Serialize};

use super::object::{Lang, NodeRef};

/// The kinds of event a portal may register.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum EventKind {
    /// Every EMCY of every node.
    Emcy,
    /// NMT states of supervised nodes, and their silence.
    State,
    /// The state of a CAN network.
    Bus,
}

impl EventKind {
    /// Every kind.
    pub const ALL: [EventKind; 3] = [EventKind::Emcy, EventKind::State, EventKind::Bus];

    /// The name on the wire.
    pub fn name(self) -> &'static str {
        match self {
            EventKind::Emcy => "emcy",
            EventKind::State => "state",
            EventKind::Bus => "bus",
        }
    }
}

impl fmt::Display for EventKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// `reg_canopen_event` parameters.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RegEventParams {
    /// The kinds wanted (an unknown kind is a −32602).
    pub events: Vec<EventKind>,
    /// The language of EMCY texts.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lang: Option<Lang>,
}

/// `unreg_canopen_event` parameters: the kinds no longer wanted (absent: all).
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct UnregEventParams {
    /// The kinds to end; every kind when absent.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub events: Option<Vec<EventKind>>,
}

/// An NMT state as events name it (CiA 301 §7.3.2), or silence.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "kebab-case")]
pub enum NodeState {
    /// The node (re)started: its boot-up message.
    BootUp,
    /// Pre-operational.
    PreOperational,
    /// Operational.
    Operational,
    /// Stopped.
    Stopped,
    /// Its heartbeat stayed away for 1.5 periods.
    Offline,
}

impl NodeState {
    /// The name on the wire.
    pub fn name(self) -> &'static str {
        match self {
            NodeState::BootUp => "boot-up",
            NodeState::PreOperational => "pre-operational",
            NodeState::Operational => "operational",
            NodeState::Stopped => "stopped",
            NodeState::Offline => "offline",
        }
    }
}

/// The state of a CAN network as the gateway's interface sees it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(rename_all = "kebab-case")]
pub enum BusState {
    /// The controller takes part normally (also: the link came back).
    ErrorActive,
    /// Error counters above 127: the controller only listens to errors passively.
    ErrorPassive,
    /// Error counter above 255: the controller is off the bus.
    BusOff,
    /// Frames were lost in the interface's receive queue.
    Overrun,
    /// The link to the network is gone (e.g. the socketcand connection).
    Offline,
}

impl BusState {
    /// The name on the wire.
    pub fn name(self) -> &'static str {
        match self {
            BusState::ErrorActive => "error-active",
            BusState::ErrorPassive => "error-passive",
            BusState::BusOff => "bus-off",
            BusState::Overrun => "overrun",
            BusState::Offline => "offline",
        }
    }
}

/// One event. `time` is when the gateway saw it (UTC, RFC 3339 with milliseconds), kept when
/// the event waited for a portal.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(tag = "type", rename_all = "lowercase")]
pub enum Event {
    /// An EMCY message (CiA 301 §7.2.7).
    Emcy {
        /// The node that sent it.
        node: NodeRef,
        /// When.
        time: String,
        /// Error code, `0x` and four hex digits (`0x0000`: error reset).
        code: String,
        /// Error register (1001h), `0x` and two hex digits.
        register: String,
        /// The five manufacturer-specific bytes, hex.
        data: String,
        /// The error class and, where known, the fault, in the registered language.
        text: String,
    },
    /// A node's NMT state changed, or it fell silent.
    State {
        /// The node.
        node: NodeRef,
        /// When.
        time: String,
        /// Its state.
        state: NodeState,
    },
    /// A network's state changed.
    Bus {
        /// The network.
        net: u8,
        /// When.
        time: String,
        /// Its state.
        state: BusState,
    },
}

impl Event {
    /// The kind of the event.
    pub fn kind(&self) -> EventKind {
        match self {
            Event::Emcy { .. } => EventKind::Emcy,
            Event::State { .. } => EventKind::State,
            Event::Bus { .. } => EventKind::Bus,
        }
    }

    /// When it happened (ms since the epoch), if `time` reads.
    pub fn time_ms(&self) -> Option<i64> {
        let (Event::Emcy { time, .. } | Event::State { time, .. } | Event::Bus { time, .. }) = self;
        parse_time(time)
    }
}

/// The payload of a `canopen_event` notification.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct EventNotification {
    /// The event.
    pub event: Event,
}

/// `ms` since the epoch as events write it: `2026-11-23T10:11:12.345Z`.
pub fn format_time(ms: i64) -> String {
    let at = time::OffsetDateTime::from_unix_timestamp(ms.div_euclid(1000))
        .unwrap_or(time::OffsetDateTime::UNIX_EPOCH);
    format!(
        "{:04}-{:02}-{:02}T{:02}:{:02}:{:02}.{:03}Z",
        at.year(),
        u8::from(at.month()),
        at.day(),
        at.hour(),
        at.minute(),
        at.second(),
        ms.rem_euclid(1000)
    )
}

/// Read an RFC 3339 time (any offset, `Z`, any number of fraction digits; RFC 3339 §5.6) as
/// ms since the epoch.
pub fn parse_time(text: &str) -> Option<i64> {
    let at =
        time::OffsetDateTime::parse(text, &time::format_description::well_known::Rfc3339).ok()?;
    i64::try_from(at.unix_timestamp_nanos().div_euclid(1_000_000)).ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msg::NodeId;
    use serde_json::json;

    #[test]
    fn events_read_and_write_as_documented() {
        let emcy = json!({"type":"emcy","node":{"id":1,"net":1},"time":"2026-11-23T10:11:12.345Z",
            "code":"0xFF01","register":"0x21","data":"0000000000","text":"Door blocked"});
        let read: Event = serde_json::from_value(emcy.clone()).unwrap();
        assert_eq!(read.kind(), EventKind::Emcy);
        assert_eq!(serde_json::to_value(&read).unwrap(), emcy);
        let state = Event::State {
            node: NodeRef::new(NodeId::new(12).unwrap(), 1),
            time: format_time(0),
            state: NodeState::Offline,
        };
        assert_eq!(
            serde_json::to_value(&state).unwrap(),
            json!({"type":"state","node":{"id":12,"net":1},"time":"1970-01-01T00:00:00.000Z","state":"offline"})
        );
        let bus: Event = serde_json::from_value(
            json!({"type":"bus","net":1,"time":"2026-11-23T10:11:12Z","state":"bus-off"}),
        )
        .unwrap();
        assert_eq!(bus.kind(), EventKind::Bus);
        assert!(
            serde_json::from_value::<RegEventParams>(json!({"events":["emcy","door"]})).is_err()
        );
    }

    #[test]
    fn times_round_trip() {
        for ms in [0, 1_795_000_000_123, 951_782_400_999] {
            assert_eq!(parse_time(&format_time(ms)), Some(ms));
        }
        assert_eq!(
            parse_time("2026-11-23T10:11:12.3456+00:00"),
            parse_time("2026-11-23T10:11:12.345Z")
        );
        // The same moment in Central European Time, and at the other side of the date line.
        assert_eq!(
            parse_time("2026-11-23T11:11:12.345+01:00"),
            parse_time("2026-11-23T10:11:12.345Z")
        );
        assert_eq!(
            parse_time("2026-11-22T23:41:12-10:30"),
            parse_time("2026-11-23T10:11:12Z")
        );
        assert_eq!(
            parse_time("2026-11-23T10:11:12"),
            None,
            "an offset is needed"
        );
        assert_eq!(parse_time("2026-13-23T10:11:12Z"), None);
    }
}
