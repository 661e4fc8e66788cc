//! Network supervision, as a gateway or NMT master watches a CAN network (CiA 301 §7.2.8.3.2
//! heartbeat consumer, §7.2.7 EMCY consumer), sans-IO: frames, link news and time in; what
//! happened out.
//!
//! - every EMCY of every node;
//! - the NMT state of every node heard (boot-up, heartbeats). A node is supervised once its
//!   heartbeat period is known — configured, or read from its 1017h when first heard (the
//!   driver runs the SDO read: [`Supervision::ReadPeriod`]), or, when that read fails,
//!   measured between its first two heartbeats — and is offline after 1.5 periods of silence.
//!   Nodes without a heartbeat (1017h = 0) are not supervised;
//! - the network's state: error-active, error-passive, bus-off from error frames (SocketCAN
//!   classes, linux/can/error.h), overrun when frames were lost, offline while the link to the
//!   network is down (node silence is not reported meanwhile: nothing can be heard).

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use canbus::{CanId, Frame};

use crate::emcy::EmcyMessage;
use crate::heartbeat::{HeartbeatConsumer, HeartbeatEvent, NodeState};

/// The state of a supervised node.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NodeStatus {
    /// It sent its boot-up message.
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

/// The state of the network.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum BusCondition {
    /// Normal (also: the link is back).
    ErrorActive,
    /// The controller's error counters passed 127.
    ErrorPassive,
    /// The controller left the bus.
    BusOff,
    /// Frames were lost before they were read.
    Overrun,
    /// The link to the network is down.
    Offline,
}

/// What the supervisor noticed, or needs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Supervision {
    /// A node sent an EMCY.
    Emcy {
        /// The node.
        node: u8,
        /// The message.
        message: EmcyMessage,
    },
    /// A node's state changed.
    Node {
        /// The node.
        node: u8,
        /// Its state.
        status: NodeStatus,
    },
    /// The network's state changed.
    Bus(BusCondition),
    /// Read 1017h of this node and report it with [`Supervisor::period`].
    ReadPeriod(u8),
}

/// How a node's heartbeat period is known.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Period {
    /// Configured (ms; 0: not supervised).
    Configured(u16),
    /// 1017h is being read.
    Asking,
    /// The read failed: the time between the first two heartbeats will do.
    Measuring(Option<Instant>),
    /// Known (ms; 0: no heartbeat).
    Known(u16),
}

/// SocketCAN error classes (linux/can/error.h).
const ERR_CRTL: u32 = 0x04;
const ERR_BUSOFF: u32 = 0x40;
const ERR_RESTARTED: u32 = 0x100;
/// Details of `ERR_CRTL` in data byte 1.
const CRTL_OVERFLOW: u8 = 0x01 | 0x02;
const CRTL_PASSIVE: u8 = 0x10 | 0x20;
const CRTL_ACTIVE: u8 = 0x40;

/// The supervisor of one network.
#[derive(Debug, Clone)]
pub struct Supervisor {
    own: u8,
    heartbeat: HeartbeatConsumer,
    periods: BTreeMap<u8, Period>,
    link_up: bool,
    bus: BusCondition,
}

impl Supervisor {
    /// A supervisor for a network where the supervising device is node `own` (never
    /// supervised itself), with heartbeat periods configured for some nodes (ms; 0: do not
    /// supervise that node).
    pub fn new(own: u8, configured: impl IntoIterator<Item = (u8, u16)>) -> Supervisor {
        let mut s = Supervisor {
            own,
            heartbeat: HeartbeatConsumer::new(),
            periods: BTreeMap::new(),
            link_up: true,
            bus: BusCondition::ErrorActive,
        };
        for (node, ms) in configured {
            s.periods.insert(node, Period::Configured(ms));
            s.heartbeat.monitor(node, consumer_time(ms));
        }
        s
    }

    /// The nodes heard, with their states.
    pub fn nodes(&self) -> impl Iterator<Item = (u8, NodeState)> + '_ {
        self.heartbeat.table()
    }

    /// When [`Self::handle_timeout`] must be called.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.link_up
            .then(|| self.heartbeat.poll_timeout())
            .flatten()
    }

    /// Time passed: nodes whose heartbeat stayed away are offline.
    pub fn handle_timeout(&mut self, now: Instant, out: &mut Vec<Supervision>) {
        if !self.link_up {
            return;
        }
        let mut events = Vec::new();
        self.heartbeat.handle_timeout(now, &mut events);
        translate(events, out);
    }

    /// A frame from the network.
    pub fn handle_frame(&mut self, frame: &Frame, now: Instant, out: &mut Vec<Supervision>) {
        if frame.is_error() {
            if let Some(condition) = condition_of(frame) {
                self.report(condition, out);
            }
            return;
        }
        let CanId::Standard(id) = frame.id() else {
            return;
        };
        match id {
            0x081..=0x0FF => {
                if let Some((node, message)) = EmcyMessage::from_frame(frame) {
                    out.push(Supervision::Emcy { node, message });
                }
            }
            0x701..=0x77F => self.heartbeat_frame(frame, (id - 0x700) as u8, now, out),
            _ => {}
        }
    }

    fn heartbeat_frame(
        &mut self,
        frame: &Frame,
        node: u8,
        now: Instant,
        out: &mut Vec<Supervision>,
    ) {
        if node == self.own {
            return;
        }
        let boot_up = frame.data() == [0];
        let period = self.periods.get(&node).copied();
        match period {
            None => self.ask(node, out),
            Some(Period::Configured(_)) => {}
            Some(_) if boot_up => self.ask(node, out),
            Some(Period::Measuring(None)) => {
                self.periods.insert(node, Period::Measuring(Some(now)));
            }
            Some(Period::Measuring(Some(first))) => {
                let ms = u16::try_from(now.duration_since(first).as_millis()).unwrap_or(u16::MAX);
                self.supervise(node, ms);
            }
            Some(Period::Asking | Period::Known(_)) => {}
        }
        let mut events = Vec::new();
        self.heartbeat.handle(frame, now, &mut events);
        translate(events, out);
    }

    fn ask(&mut self, node: u8, out: &mut Vec<Supervision>) {
        self.periods.insert(node, Period::Asking);
        out.push(Supervision::ReadPeriod(node));
    }

    /// Supervise `node` with a heartbeat of `ms` (0: only follow its state).
    fn supervise(&mut self, node: u8, ms: u16) {
        self.periods.insert(node, Period::Known(ms));
        self.heartbeat.monitor(node, consumer_time(ms));
    }

    /// The answer to [`Supervision::ReadPeriod`]: 1017h of `node` in ms, or `None` when it
    /// could not be read (the period is then measured).
    pub fn period(&mut self, node: u8, ms: Option<u16>) {
        if self.periods.get(&node) != Some(&Period::Asking) {
            return;
        }
        match ms {
            Some(ms) => self.supervise(node, ms),
            None => {
                self.periods.insert(node, Period::Measuring(None));
            }
        }
    }

    /// The link to the network went down (`false`) or came back.
    pub fn link(&mut self, up: bool, now: Instant, out: &mut Vec<Supervision>) {
        if up == self.link_up {
            return;
        }
        self.link_up = up;
        if up {
            // Silence while the link was down says nothing about the nodes.
            self.heartbeat.rearm(now);
            self.report(BusCondition::ErrorActive, out);
        } else {
            self.report(BusCondition::Offline, out);
        }
    }

    /// Frames were lost before they were read.
    pub fn overrun(&mut self, out: &mut Vec<Supervision>) {
        out.push(Supervision::Bus(BusCondition::Overrun));
    }

    fn report(&mut self, condition: BusCondition, out: &mut Vec<Supervision>) {
        if condition == BusCondition::Overrun {
            out.push(Supervision::Bus(condition));
        } else if condition != self.bus {
            self.bus = condition;
            out.push(Supervision::Bus(condition));
        }
    }
}

/// 1.5 heartbeat periods of `ms` (none for 0: no heartbeat, not supervised).
fn consumer_time(ms: u16) -> Option<Duration> {
    (ms > 0).then(|| Duration::from_millis(u64::from(ms) * 3 / 2))
}

/// What an error frame says about the network, if anything a person should know.
fn condition_of(frame: &Frame) -> Option<BusCondition> {
    let class = frame.raw_id();
    let detail = frame.data().get(1).copied().unwrap_or(0);
    if class & ERR_BUSOFF != 0 {
        Some(BusCondition::BusOff)
    } else if class & ERR_RESTARTED != 0 {
        Some(BusCondition::ErrorActive)
    } else if class & ERR_CRTL == 0 {
        None
    } else if detail & CRTL_OVERFLOW != 0 {
        Some(BusCondition::Overrun)
    } else if detail & CRTL_PASSIVE != 0 {
        Some(BusCondition::ErrorPassive)
    } else if detail & CRTL_ACTIVE != 0 {
        Some(BusCondition::ErrorActive)
    } else {
        None
    }
}

/// The heartbeat consumer's news as node states (a boot-up is reported once, as boot-up).
fn translate(events: Vec<HeartbeatEvent>, out: &mut Vec<Supervision>) {
    for event in events {
        let (node, status) = match event {
            HeartbeatEvent::BootUp { node } => (node, NodeStatus::BootUp),
            HeartbeatEvent::StateChanged { node, new, .. } => match new {
                NodeState::PreOperational => (node, NodeStatus::PreOperational),
                NodeState::Operational => (node, NodeStatus::Operational),
                NodeState::Stopped => (node, NodeStatus::Stopped),
                NodeState::Offline => (node, NodeStatus::Offline),
                NodeState::BootUp | NodeState::Unknown => continue,
            },
            HeartbeatEvent::Timeout { .. } | HeartbeatEvent::Recovered { .. } => continue,
        };
        out.push(Supervision::Node { node, status });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::heartbeat::heartbeat_frame;
    use crate::nmt::{boot_up_frame, NmtState};

    fn run(s: &mut Supervisor, frame: &Frame, now: Instant) -> Vec<Supervision> {
        let mut out = Vec::new();
        s.handle_frame(frame, now, &mut out);
        out
    }

    fn later(s: &mut Supervisor, now: Instant) -> Vec<Supervision> {
        let mut out = Vec::new();
        s.handle_timeout(now, &mut out);
        out
    }

    fn status(node: u8, status: NodeStatus) -> Supervision {
        Supervision::Node { node, status }
    }

    #[test]
    fn a_node_is_supervised_with_the_period_of_its_1017h() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut s = Supervisor::new(9, []);
        assert_eq!(
            run(&mut s, &boot_up_frame(12), t0),
            [Supervision::ReadPeriod(12), status(12, NodeStatus::BootUp)]
        );
        s.period(12, Some(200));
        let hb = heartbeat_frame(12, NmtState::Operational);
        assert_eq!(
            run(&mut s, &hb, t0 + ms(200)),
            [status(12, NodeStatus::Operational)]
        );
        assert_eq!(s.poll_timeout(), Some(t0 + ms(500)), "1.5 periods");
        assert!(later(&mut s, t0 + ms(499)).is_empty());
        assert_eq!(
            later(&mut s, t0 + ms(500)),
            [status(12, NodeStatus::Offline)]
        );
        // Back: boot-up, asked again (its 1017h may have changed).
        assert_eq!(
            run(&mut s, &boot_up_frame(12), t0 + ms(900)),
            [Supervision::ReadPeriod(12), status(12, NodeStatus::BootUp)]
        );
        // Its own heartbeat is not supervised.
        assert!(run(&mut s, &heartbeat_frame(9, NmtState::Operational), t0).is_empty());
    }

    #[test]
    fn without_1017h_the_period_is_measured_and_zero_means_unsupervised() {
        let t0 = Instant::now();
        let ms = Duration::from_millis;
        let mut s = Supervisor::new(9, [(5, 0)]);
        let hb = heartbeat_frame(3, NmtState::PreOperational);
        assert_eq!(
            run(&mut s, &hb, t0),
            [
                Supervision::ReadPeriod(3),
                status(3, NodeStatus::PreOperational)
            ]
        );
        s.period(3, None);
        run(&mut s, &hb, t0 + ms(100));
        run(&mut s, &hb, t0 + ms(200));
        assert_eq!(s.poll_timeout(), Some(t0 + ms(350)));
        // Configured 0: followed, never offline.
        run(&mut s, &heartbeat_frame(5, NmtState::Operational), t0);
        assert!(later(&mut s, t0 + Duration::from_secs(60))
            .iter()
            .all(|e| *e != status(5, NodeStatus::Offline)));
    }

    #[test]
    fn the_network_state_comes_from_error_frames_and_the_link() {
        let t0 = Instant::now();
        let mut s = Supervisor::new(9, [(12, 100)]);
        run(&mut s, &heartbeat_frame(12, NmtState::Operational), t0);
        let passive = Frame::error(ERR_CRTL, &[0, 0x10]).unwrap();
        assert_eq!(
            run(&mut s, &passive, t0),
            [Supervision::Bus(BusCondition::ErrorPassive)]
        );
        assert!(run(&mut s, &passive, t0).is_empty(), "only changes");
        let off = Frame::error(ERR_BUSOFF, &[]).unwrap();
        assert_eq!(
            run(&mut s, &off, t0),
            [Supervision::Bus(BusCondition::BusOff)]
        );
        let mut out = Vec::new();
        s.link(false, t0, &mut out);
        assert_eq!(out, [Supervision::Bus(BusCondition::Offline)]);
        assert_eq!(s.poll_timeout(), None, "no node goes offline meanwhile");
        out.clear();
        let back = t0 + Duration::from_secs(10);
        s.link(true, back, &mut out);
        assert_eq!(out, [Supervision::Bus(BusCondition::ErrorActive)]);
        assert_eq!(
            s.poll_timeout(),
            Some(back + Duration::from_millis(150)),
            "silence counted from the link's return"
        );
        let emcy = Frame::standard(0x08C, &[0x01, 0xFF, 0x21, 0, 0, 0, 0, 0]).unwrap();
        assert!(matches!(
            run(&mut s, &emcy, back)[..],
            [Supervision::Emcy { node: 12, message }] if message.code == 0xFF01
        ));
    }
}
