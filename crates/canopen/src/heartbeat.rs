//! Heartbeat (CiA 301 §7.2.8.3.2.2): the producer (0x1017) and the consumer table (0x1016).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use canbus::{CanId, Frame};

use crate::nmt::NmtState;

/// Heartbeat producer: one frame every period, carrying the node's NMT state.
#[derive(Debug, Clone)]
pub struct HeartbeatProducer {
    node_id: u8,
    period: Option<Duration>,
    next: Option<Instant>,
}

impl HeartbeatProducer {
    /// A producer for `node_id`, off until a period is set.
    pub fn new(node_id: u8) -> Self {
        HeartbeatProducer {
            node_id,
            period: None,
            next: None,
        }
    }

    /// Set the producer time from 0x1017 (milliseconds; 0 disables). The first heartbeat
    /// follows one period after `now`.
    pub fn set_period_ms(&mut self, ms: u16, now: Instant) {
        self.period = (ms > 0).then(|| Duration::from_millis(ms.into()));
        self.next = self.period.map(|p| now + p);
    }

    /// When [`Self::handle_timeout`] must be called.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.next
    }

    /// Send the heartbeat if one is due. The next one is scheduled a period after the one due,
    /// not after `now`, so a late call does not make the producer drift.
    pub fn handle_timeout(&mut self, now: Instant, state: NmtState, out: &mut Vec<Frame>) {
        let (Some(next), Some(period)) = (self.next, self.period) else {
            return;
        };
        if now < next {
            return;
        }
        self.next = Some(crate::tick::next_tick(next, period, now));
        out.push(heartbeat_frame(self.node_id, state));
    }
}

/// A heartbeat frame of `node` in `state`.
pub fn heartbeat_frame(node: u8, state: NmtState) -> Frame {
    Frame::standard(0x700 + u16::from(node & 0x7F), &[state.code()])
        .unwrap_or_else(|_| unreachable!("0x77F at most"))
}

/// What the consumer table knows about a node.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NodeState {
    /// Never heard.
    Unknown,
    /// Sent its boot-up message.
    BootUp,
    /// Heartbeat says pre-operational.
    PreOperational,
    /// Heartbeat says operational.
    Operational,
    /// Heartbeat says stopped.
    Stopped,
    /// Its heartbeat did not come within the consumer time.
    Offline,
}

impl NodeState {
    fn from_code(code: u8) -> Option<Self> {
        Some(match NmtState::from_code(code)? {
            NmtState::Initialising => NodeState::BootUp,
            NmtState::PreOperational => NodeState::PreOperational,
            NmtState::Operational => NodeState::Operational,
            NmtState::Stopped => NodeState::Stopped,
        })
    }
}

/// A change the consumer noticed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HeartbeatEvent {
    /// A node sent its boot-up message: it (re)started, whatever the table knew before.
    BootUp {
        /// The node.
        node: u8,
    },
    /// A node's state changed.
    StateChanged {
        /// The node.
        node: u8,
        /// Before.
        old: NodeState,
        /// Now.
        new: NodeState,
    },
    /// A monitored node missed its consumer time (CiA 301: heartbeat event; the PLC manual
    /// reports it as EMCY 0x8130 with manufacturer bytes `00 NN 00 00 00`).
    Timeout {
        /// The node.
        node: u8,
    },
    /// A node that had timed out is heard again (the EMCY is cleared).
    Recovered {
        /// The node.
        node: u8,
    },
}

#[derive(Debug, Clone)]
struct Entry {
    state: NodeState,
    consumer_time: Option<Duration>,
    deadline: Option<Instant>,
    last_seen: Option<Instant>,
}

/// The heartbeat consumer: a table of every node heard, with per-node consumer times for the
/// monitored ones (CiA 301 0x1016: the timer starts with the first heartbeat received).
#[derive(Debug, Clone, Default)]
pub struct HeartbeatConsumer {
    nodes: BTreeMap<u8, Entry>,
}

impl HeartbeatConsumer {
    /// An empty table.
    pub fn new() -> Self {
        Self::default()
    }

    /// Monitor `node` with `consumer_time` (`None` or zero: track state only, no timeout).
    pub fn monitor(&mut self, node: u8, consumer_time: Option<Duration>) {
        let entry = self.nodes.entry(node).or_insert(Entry {
            state: NodeState::Unknown,
            consumer_time: None,
            deadline: None,
            last_seen: None,
        });
        entry.consumer_time = consumer_time.filter(|t| !t.is_zero());
        entry.deadline = match (entry.last_seen, entry.consumer_time) {
            (Some(seen), Some(t)) if entry.state != NodeState::Offline => Some(seen + t),
            _ => None,
        };
    }

    /// Configure from a 0x1016 entry value: node-ID in bits 16–23, time in ms in bits 0–15.
    pub fn monitor_entry(&mut self, entry: u32) {
        let node = ((entry >> 16) & 0xFF) as u8;
        let ms = entry & 0xFFFF;
        if (1..=127).contains(&node) {
            self.monitor(node, Some(Duration::from_millis(ms.into())));
        }
    }

    /// The state of `node` as last heard.
    pub fn state(&self, node: u8) -> NodeState {
        self.nodes
            .get(&node)
            .map_or(NodeState::Unknown, |e| e.state)
    }

    /// When `node` was last heard.
    pub fn last_seen(&self, node: u8) -> Option<Instant> {
        self.nodes.get(&node).and_then(|e| e.last_seen)
    }

    /// Every node in the table with its state.
    pub fn table(&self) -> impl Iterator<Item = (u8, NodeState)> + '_ {
        self.nodes.iter().map(|(n, e)| (*n, e.state))
    }

    /// When [`Self::handle_timeout`] must be called.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.nodes.values().filter_map(|e| e.deadline).min()
    }

    /// Handle a frame; heartbeat and boot-up frames update the table.
    pub fn handle(&mut self, frame: &Frame, now: Instant, events: &mut Vec<HeartbeatEvent>) {
        let (CanId::Standard(id @ 0x701..=0x77F), [code]) = (frame.id(), frame.data()) else {
            return;
        };
        let Some(new) = NodeState::from_code(*code) else {
            return;
        };
        let node = (id - 0x700) as u8;
        let entry = self.nodes.entry(node).or_insert(Entry {
            state: NodeState::Unknown,
            consumer_time: None,
            deadline: None,
            last_seen: None,
        });
        if entry.state == NodeState::Offline {
            events.push(HeartbeatEvent::Recovered { node });
        }
        if new == NodeState::BootUp {
            events.push(HeartbeatEvent::BootUp { node });
        }
        entry.last_seen = Some(now);
        entry.deadline = entry.consumer_time.map(|t| now + t);
        if entry.state != new {
            events.push(HeartbeatEvent::StateChanged {
                node,
                old: entry.state,
                new,
            });
            entry.state = new;
        }
    }

    /// Start every running consumer timer again from `now` (after a time in which nothing
    /// could be heard, such as a lost link): nodes heard before get a full consumer time.
    pub fn rearm(&mut self, now: Instant) {
        for entry in self.nodes.values_mut() {
            if entry.state != NodeState::Offline && entry.last_seen.is_some() {
                entry.deadline = entry.consumer_time.map(|t| now + t);
            }
        }
    }

    /// Mark nodes whose consumer time has passed as offline.
    pub fn handle_timeout(&mut self, now: Instant, events: &mut Vec<HeartbeatEvent>) {
        for (node, entry) in &mut self.nodes {
            if entry.deadline.is_some_and(|d| now >= d) {
                entry.deadline = None;
                events.push(HeartbeatEvent::Timeout { node: *node });
                events.push(HeartbeatEvent::StateChanged {
                    node: *node,
                    old: entry.state,
                    new: NodeState::Offline,
                });
                entry.state = NodeState::Offline;
            }
        }
    }
}

/// The EMCY a consumer timeout raises: error code 0x8130 (life guard / heartbeat error) and the
/// manufacturer bytes `00 NN 00 00 00` with the node-ID, as the PLC manual describes.
pub fn timeout_emcy(node: u8) -> (u16, [u8; 5]) {
    (
        crate::emcy::codes::HEARTBEAT,
        [0x00, node, 0x00, 0x00, 0x00],
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn due(p: &mut HeartbeatProducer, now: Instant, state: NmtState) -> Option<Frame> {
        let mut out = Vec::new();
        p.handle_timeout(now, state, &mut out);
        out.pop()
    }

    #[test]
    fn producer_keeps_its_period_without_drift() {
        let t0 = Instant::now();
        let mut p = HeartbeatProducer::new(9);
        assert_eq!(p.poll_timeout(), None, "0x1017 = 0: off");
        p.set_period_ms(100, t0);
        assert_eq!(p.poll_timeout(), Some(t0 + Duration::from_millis(100)));
        assert_eq!(
            due(
                &mut p,
                t0 + Duration::from_millis(99),
                NmtState::Operational
            ),
            None
        );
        // Called 7 ms late: the frame goes out and the next stays on the 100 ms grid.
        let f = due(
            &mut p,
            t0 + Duration::from_millis(107),
            NmtState::Operational,
        )
        .unwrap();
        assert_eq!(f, Frame::standard(0x709, &[0x05]).unwrap());
        assert_eq!(p.poll_timeout(), Some(t0 + Duration::from_millis(200)));
        // Suspended for a second: no burst of ten frames, one frame and a fresh schedule.
        let late = t0 + Duration::from_millis(1250);
        assert!(due(&mut p, late, NmtState::PreOperational).is_some());
        assert_eq!(p.poll_timeout(), Some(late + Duration::from_millis(100)));
        p.set_period_ms(0, late);
        assert_eq!(p.poll_timeout(), None);
    }

    #[test]
    fn consumer_table_timeouts_and_recovery() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut c = HeartbeatConsumer::new();
        c.monitor_entry(0x0001_01F4); // node 1, 500 ms
        let mut ev = Vec::new();
        assert_eq!(
            c.poll_timeout(),
            None,
            "timer starts with the first heartbeat"
        );
        c.handle(&Frame::standard(0x701, &[0x00]).unwrap(), t0, &mut ev);
        c.handle(
            &Frame::standard(0x701, &[0x7F]).unwrap(),
            t0 + ms(10),
            &mut ev,
        );
        c.handle(
            &Frame::standard(0x70C, &[0x05]).unwrap(),
            t0 + ms(20),
            &mut ev,
        );
        assert_eq!(
            ev,
            vec![
                HeartbeatEvent::BootUp { node: 1 },
                HeartbeatEvent::StateChanged {
                    node: 1,
                    old: NodeState::Unknown,
                    new: NodeState::BootUp
                },
                HeartbeatEvent::StateChanged {
                    node: 1,
                    old: NodeState::BootUp,
                    new: NodeState::PreOperational
                },
                HeartbeatEvent::StateChanged {
                    node: 12,
                    old: NodeState::Unknown,
                    new: NodeState::Operational
                },
            ]
        );
        ev.clear();
        assert_eq!(
            c.poll_timeout(),
            Some(t0 + ms(510)),
            "node 12 is tracked but not monitored"
        );
        c.handle_timeout(t0 + ms(509), &mut ev);
        assert!(ev.is_empty());
        c.handle_timeout(t0 + ms(510), &mut ev);
        assert_eq!(
            ev,
            vec![
                HeartbeatEvent::Timeout { node: 1 },
                HeartbeatEvent::StateChanged {
                    node: 1,
                    old: NodeState::PreOperational,
                    new: NodeState::Offline
                },
            ]
        );
        assert_eq!(c.poll_timeout(), None, "one timeout per outage");
        ev.clear();
        c.handle(
            &Frame::standard(0x701, &[0x05]).unwrap(),
            t0 + ms(2000),
            &mut ev,
        );
        assert_eq!(
            ev,
            vec![
                HeartbeatEvent::Recovered { node: 1 },
                HeartbeatEvent::StateChanged {
                    node: 1,
                    old: NodeState::Offline,
                    new: NodeState::Operational
                },
            ]
        );
        assert_eq!(c.poll_timeout(), Some(t0 + ms(2500)));
        assert_eq!(c.state(12), NodeState::Operational);
        assert_eq!(c.table().count(), 2);
        assert_eq!(timeout_emcy(1), (0x8130, [0, 1, 0, 0, 0]));
    }

    #[test]
    fn other_frames_are_ignored() {
        let mut c = HeartbeatConsumer::new();
        let mut ev = Vec::new();
        let now = Instant::now();
        for f in [
            Frame::standard(0x700, &[0x05]).unwrap(),
            Frame::standard(0x701, &[0x05, 0]).unwrap(),
            Frame::standard(0x701, &[0x33]).unwrap(),
            Frame::standard(0x181, &[0x05]).unwrap(),
        ] {
            c.handle(&f, now, &mut ev);
        }
        assert!(ev.is_empty());
    }
}
