//! Bus events on the gateway's side (docs/PROTOCOL.md §Events): what the driver saw on its
//! networks ([`BusEvent`]), and the [`EventQueue`] that keeps them — with their original time —
//! until a portal registers for them. The queue belongs to the gateway, not to a connection:
//! events that happen while the cloud is away are delivered, in order, after the next
//! `reg_canopen_event`.

use std::collections::VecDeque;

use crate::meta::Texts;
use crate::msg::{self, BusState, Event, EventKind, NodeRef, NodeState};

use super::metadata::Metadata;

/// Events kept while no portal takes them, unless configured.
pub const QUEUED_EVENTS: usize = 1000;

/// What happened.
#[derive(Debug, Clone, PartialEq)]
pub enum Happening {
    /// A node sent an EMCY (CiA 301 §7.2.7).
    Emcy {
        /// The node.
        node: NodeRef,
        /// Error code (0: error reset).
        code: u16,
        /// Error register.
        register: u8,
        /// Manufacturer-specific bytes.
        data: [u8; 5],
        /// What the code means, per language.
        text: Texts,
    },
    /// A supervised node's state changed.
    State {
        /// The node.
        node: NodeRef,
        /// Its state.
        state: NodeState,
    },
    /// A network's state changed.
    Bus {
        /// The network.
        net: u8,
        /// Its state.
        state: BusState,
    },
}

/// One event with the time it happened (ms since the epoch).
#[derive(Debug, Clone, PartialEq)]
pub struct BusEvent {
    /// When the gateway saw it.
    pub time_ms: i64,
    /// What.
    pub what: Happening,
}

impl BusEvent {
    /// Its kind.
    pub fn kind(&self) -> EventKind {
        match self.what {
            Happening::Emcy { .. } => EventKind::Emcy,
            Happening::State { .. } => EventKind::State,
            Happening::Bus { .. } => EventKind::Bus,
        }
    }

    /// The event as the connector writes it, texts in `preferred`, else `alternate`, else
    /// English.
    pub fn to_wire(&self, metadata: &dyn Metadata, preferred: &str, alternate: &str) -> Event {
        let time = msg::format_time(self.time_ms);
        match &self.what {
            Happening::Emcy {
                node,
                code,
                register,
                data,
                text,
            } => Event::Emcy {
                node: *node,
                time,
                code: format!("0x{code:04X}"),
                register: format!("0x{register:02X}"),
                data: data.iter().map(|b| format!("{b:02X}")).collect(),
                text: metadata
                    .text(text, preferred, alternate)
                    .map(|(_, t)| t.to_owned())
                    .unwrap_or_default(),
            },
            Happening::State { node, state } => Event::State {
                node: *node,
                time,
                state: *state,
            },
            Happening::Bus { net, state } => Event::Bus {
                net: *net,
                time,
                state: *state,
            },
        }
    }
}

/// Events waiting for a portal: at most `capacity`; when full the oldest goes and is counted.
#[derive(Debug, Clone)]
pub struct EventQueue {
    events: VecDeque<BusEvent>,
    capacity: usize,
    dropped: u64,
}

impl Default for EventQueue {
    fn default() -> Self {
        EventQueue::new(QUEUED_EVENTS)
    }
}

impl EventQueue {
    /// An empty queue for `capacity` events (at least one).
    pub fn new(capacity: usize) -> EventQueue {
        EventQueue {
            events: VecDeque::new(),
            capacity: capacity.max(1),
            dropped: 0,
        }
    }

    /// Keep `event`; when full, the oldest makes room.
    pub fn push(&mut self, event: BusEvent) {
        if self.events.len() == self.capacity {
            self.events.pop_front();
            self.dropped += 1;
        }
        self.events.push_back(event);
    }

    /// Everything waiting, oldest first, and how many were dropped since the last take.
    pub fn take(&mut self) -> (Vec<BusEvent>, u64) {
        let dropped = std::mem::take(&mut self.dropped);
        (self.events.drain(..).collect(), dropped)
    }

    /// Events waiting.
    pub fn len(&self) -> usize {
        self.events.len()
    }

    /// Whether none waits.
    pub fn is_empty(&self) -> bool {
        self.events.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bus(time_ms: i64) -> BusEvent {
        BusEvent {
            time_ms,
            what: Happening::Bus {
                net: 1,
                state: BusState::ErrorActive,
            },
        }
    }

    #[test]
    fn the_oldest_go_first_and_are_counted() {
        let mut q = EventQueue::new(3);
        for t in 0..5 {
            q.push(bus(t));
        }
        let (events, dropped) = q.take();
        assert_eq!(dropped, 2);
        assert_eq!(
            events.iter().map(|e| e.time_ms).collect::<Vec<_>>(),
            [2, 3, 4]
        );
        assert!(q.is_empty());
        assert_eq!(q.take().1, 0, "counted once");
    }
}
