//! Node guarding and life guarding (CiA 301 §7.2.8.3.2.1), sans-IO.
//!
//! The master sends a remote frame on 0x700 + node-ID every guard time; the node answers with
//! its NMT state and a toggle bit that alternates (starting at 0). The master declares the node
//! lost when `life time factor` consecutive requests go unanswered (or answered with the wrong
//! toggle); the node declares *life guarding* lost when no request comes within guard time ×
//! life time factor (0x100C × 0x100D). Remote frames cannot travel over socketcand: guarding
//! needs SocketCAN or the in-process bus.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use canbus::{CanId, Frame};

use crate::nmt::NmtState;

/// What guarding noticed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GuardEvent {
    /// Master side: `node` stopped answering (or answered with a wrong toggle bit).
    NodeLost {
        /// The node.
        node: u8,
    },
    /// Master side: `node` answers again.
    NodeRecovered {
        /// The node.
        node: u8,
    },
    /// Master side: the state `node` reported changed.
    StateChanged {
        /// The node.
        node: u8,
        /// Its NMT state.
        state: NmtState,
    },
    /// Node side: the master stopped guarding this node.
    LifeGuardingLost,
    /// Node side: guard requests come again.
    LifeGuardingResumed,
}

fn guard_id(node: u8) -> CanId {
    CanId::Standard(0x700 + u16::from(node & 0x7F))
}

/// The node side: answers guard requests and watches that they keep coming.
#[derive(Debug, Clone)]
pub struct GuardingSlave {
    node_id: u8,
    toggle: bool,
    life_time: Option<Duration>,
    deadline: Option<Instant>,
    lost: bool,
}

impl GuardingSlave {
    /// A node that answers guard requests; life guarding is off until configured.
    pub fn new(node_id: u8) -> Self {
        GuardingSlave {
            node_id,
            toggle: false,
            life_time: None,
            deadline: None,
            lost: false,
        }
    }

    /// Apply 0x100C (guard time, ms) and 0x100D (life time factor); either 0 turns life guarding
    /// off. It starts with the first guard request.
    pub fn configure(&mut self, guard_time_ms: u16, factor: u8) {
        self.life_time = (guard_time_ms > 0 && factor > 0)
            .then(|| Duration::from_millis(u64::from(guard_time_ms) * u64::from(factor)));
        if self.life_time.is_none() {
            self.deadline = None;
        }
    }

    /// Answer a guard request (a remote frame on 0x700 + node-ID).
    pub fn handle(
        &mut self,
        frame: &Frame,
        state: NmtState,
        now: Instant,
        out: &mut Vec<Frame>,
        events: &mut Vec<GuardEvent>,
    ) {
        if !frame.is_remote() || frame.id() != guard_id(self.node_id) {
            return;
        }
        if self.lost {
            self.lost = false;
            events.push(GuardEvent::LifeGuardingResumed);
        }
        self.deadline = self.life_time.map(|t| now + t);
        let byte = state.code() | if self.toggle { 0x80 } else { 0 };
        self.toggle = !self.toggle;
        out.extend(Frame::new(guard_id(self.node_id), &[byte]).ok());
    }

    /// When [`Self::handle_timeout`] must be called.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.deadline
    }

    /// Report life guarding lost once the life time passed without a request.
    pub fn handle_timeout(&mut self, now: Instant, events: &mut Vec<GuardEvent>) {
        if self.deadline.is_some_and(|d| now >= d) {
            self.deadline = None;
            self.lost = true;
            events.push(GuardEvent::LifeGuardingLost);
        }
    }
}

#[derive(Debug, Clone)]
struct Guarded {
    guard_time: Duration,
    factor: u8,
    next_request: Instant,
    awaiting: bool,
    missed: u8,
    expected_toggle: bool,
    state: Option<NmtState>,
    lost: bool,
}

impl Guarded {
    /// An answer did not come (or came wrong): lost after `factor` in a row.
    fn missed(&mut self, node: u8, events: &mut Vec<GuardEvent>) {
        self.missed = self.missed.saturating_add(1);
        if self.missed >= self.factor && !self.lost {
            self.lost = true;
            events.push(GuardEvent::NodeLost { node });
        }
    }
}

/// The master side: guards any number of nodes.
#[derive(Debug, Clone, Default)]
pub struct GuardingMaster {
    nodes: BTreeMap<u8, Guarded>,
}

impl GuardingMaster {
    /// Guard nobody yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Guard `node` every `guard_time`, declaring it lost after `factor` missed answers;
    /// `factor` 0 stops guarding it.
    pub fn guard(&mut self, node: u8, guard_time: Duration, factor: u8, now: Instant) {
        if factor == 0 || guard_time.is_zero() {
            self.nodes.remove(&node);
            return;
        }
        self.nodes.insert(
            node,
            Guarded {
                guard_time,
                factor,
                next_request: now,
                awaiting: false,
                missed: 0,
                expected_toggle: false,
                state: None,
                lost: false,
            },
        );
    }

    /// When [`Self::handle_timeout`] must be called.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.nodes.values().map(|g| g.next_request).min()
    }

    /// Send the guard requests that are due; count unanswered ones.
    pub fn handle_timeout(
        &mut self,
        now: Instant,
        out: &mut Vec<Frame>,
        events: &mut Vec<GuardEvent>,
    ) {
        for (&node, g) in &mut self.nodes {
            if now < g.next_request {
                continue;
            }
            if g.awaiting {
                g.missed(node, events);
            }
            if let Ok(f) = Frame::remote(guard_id(node), 1) {
                out.push(f);
            }
            g.awaiting = true;
            g.next_request = crate::tick::next_tick(g.next_request, g.guard_time, now);
        }
    }

    /// Take a guard answer.
    pub fn handle(&mut self, frame: &Frame, events: &mut Vec<GuardEvent>) {
        let (CanId::Standard(id @ 0x701..=0x77F), [byte]) = (frame.id(), frame.data()) else {
            return;
        };
        let node = (id - 0x700) as u8;
        let Some(g) = self.nodes.get_mut(&node) else {
            return;
        };
        if !g.awaiting || frame.is_remote() {
            return; // a heartbeat or someone else's traffic
        }
        g.awaiting = false;
        let toggle = byte & 0x80 != 0;
        if toggle != g.expected_toggle {
            // A toggle error counts as a missed answer; resynchronise to what the node sent.
            g.missed(node, events);
            g.expected_toggle = !toggle;
            return;
        }
        g.expected_toggle = !g.expected_toggle;
        g.missed = 0;
        if g.lost {
            g.lost = false;
            events.push(GuardEvent::NodeRecovered { node });
        }
        let state = NmtState::from_code(*byte);
        if state.is_some() && state != g.state {
            g.state = state;
            if let Some(state) = state {
                events.push(GuardEvent::StateChanged { node, state });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn master_and_slave_in_simulated_time() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut master = GuardingMaster::new();
        let mut slave = GuardingSlave::new(4);
        slave.configure(100, 3); // life time 300 ms
        master.guard(4, ms(100), 3, t0);
        let (mut out, mut ev) = (Vec::new(), Vec::new());
        let mut answered = Vec::new();
        // 5 rounds with answers.
        for k in 0..5u32 {
            let now = t0 + ms(100) * k;
            out.clear();
            master.handle_timeout(now, &mut out, &mut ev);
            assert_eq!(out.len(), 1);
            assert!(out[0].is_remote() && out[0].id() == CanId::Standard(0x704));
            let mut replies = Vec::new();
            slave.handle(&out[0], NmtState::Operational, now, &mut replies, &mut ev);
            let reply = replies.pop().unwrap();
            answered.push(reply.data()[0]);
            master.handle(&reply, &mut ev);
        }
        assert_eq!(
            answered,
            vec![0x05, 0x85, 0x05, 0x85, 0x05],
            "toggle alternates from 0"
        );
        assert_eq!(
            ev,
            vec![GuardEvent::StateChanged {
                node: 4,
                state: NmtState::Operational
            }]
        );
        ev.clear();
        // The node goes silent: lost after 3 unanswered requests.
        for k in 5..9u32 {
            out.clear();
            master.handle_timeout(t0 + ms(100) * k, &mut out, &mut ev);
        }
        assert_eq!(ev, vec![GuardEvent::NodeLost { node: 4 }]);
        ev.clear();
        // The master goes silent: the slave's life guarding runs out 300 ms after the last request.
        assert_eq!(slave.poll_timeout(), Some(t0 + ms(400) + ms(300)));
        slave.handle_timeout(t0 + ms(700), &mut ev);
        assert_eq!(ev, vec![GuardEvent::LifeGuardingLost]);
        ev.clear();
        // Both come back.
        out.clear();
        master.handle_timeout(t0 + ms(900), &mut out, &mut ev);
        let mut replies = Vec::new();
        slave.handle(
            &out[0],
            NmtState::Stopped,
            t0 + ms(900),
            &mut replies,
            &mut ev,
        );
        let reply = replies.pop().unwrap();
        master.handle(&reply, &mut ev);
        assert_eq!(
            ev,
            vec![
                GuardEvent::LifeGuardingResumed,
                GuardEvent::NodeRecovered { node: 4 },
                GuardEvent::StateChanged {
                    node: 4,
                    state: NmtState::Stopped
                }
            ]
        );
    }

    #[test]
    fn toggle_errors_count_as_missed() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut master = GuardingMaster::new();
        master.guard(4, ms(100), 2, t0);
        let (mut out, mut ev) = (Vec::new(), Vec::new());
        for k in 0..3u32 {
            master.handle_timeout(t0 + ms(100) * k, &mut out, &mut ev);
            // A node that always answers with toggle 1.
            master.handle(&Frame::standard(0x704, &[0x85]).unwrap(), &mut ev);
        }
        master.handle_timeout(t0 + ms(300), &mut out, &mut ev);
        assert!(ev.contains(&GuardEvent::NodeLost { node: 4 }), "{ev:?}");
        // Heartbeats (no request outstanding) are not guard answers.
        let mut quiet = GuardingMaster::new();
        quiet.guard(5, ms(100), 2, t0);
        quiet.handle(&Frame::standard(0x705, &[0x05]).unwrap(), &mut ev);
        assert_eq!(quiet.poll_timeout(), Some(t0));
    }
}
