//! Layer setting services (CiA 305), sans-IO: the slave state machine and the master's frames.
//!
//! Master → slaves on 0x7E5, slave → master on 0x7E4, 8 bytes each, byte 0 the command
//! specifier. A slave is in the *waiting* state until switched to *configuration* globally or
//! selectively (by its LSS address: vendor-ID, product code, revision, serial number) or found by
//! Fastscan; in configuration it accepts a node-ID and bit timing, activates the bit timing,
//! stores the configuration and answers inquiries.

use canbus::{CanId, Frame};

/// Master → slave COB-ID.
pub const MASTER_ID: CanId = CanId::Standard(0x7E5);
/// Slave → master COB-ID.
pub const SLAVE_ID: CanId = CanId::Standard(0x7E4);
/// The node-ID of a slave without one.
pub const UNCONFIGURED: u8 = 0xFF;

/// Command specifiers (CiA 305 §6).
#[allow(missing_docs)]
pub mod cs {
    pub const SWITCH_GLOBAL: u8 = 0x04;
    pub const CONFIGURE_NODE_ID: u8 = 0x11;
    pub const CONFIGURE_BIT_TIMING: u8 = 0x13;
    pub const ACTIVATE_BIT_TIMING: u8 = 0x15;
    pub const STORE: u8 = 0x17;
    pub const SWITCH_SELECTIVE_VENDOR: u8 = 0x40;
    pub const SWITCH_SELECTIVE_SERIAL: u8 = 0x43;
    pub const SWITCH_SELECTIVE_RESPONSE: u8 = 0x44;
    pub const IDENTIFY_VENDOR: u8 = 0x46;
    pub const IDENTIFY_SERIAL_HIGH: u8 = 0x4B;
    pub const IDENTIFY_NON_CONFIGURED: u8 = 0x4C;
    pub const IDENTIFY_RESPONSE: u8 = 0x4F;
    pub const IDENTIFY_NON_CONFIGURED_RESPONSE: u8 = 0x50;
    pub const FASTSCAN: u8 = 0x51;
    pub const INQUIRE_VENDOR: u8 = 0x5A;
    pub const INQUIRE_SERIAL: u8 = 0x5D;
    pub const INQUIRE_NODE_ID: u8 = 0x5E;
}

/// CiA 305 bit timing table: index → bit rate in bit/s (index 9 is automatic detection).
pub const BIT_TIMINGS: [Option<u32>; 10] = [
    Some(1_000_000),
    Some(800_000),
    Some(500_000),
    Some(250_000),
    Some(125_000),
    None,
    Some(50_000),
    Some(20_000),
    Some(10_000),
    None,
];

/// A frame from the master.
pub fn request(command: u8, payload: [u8; 7]) -> Frame {
    let mut d = [0u8; 8];
    d[0] = command;
    d[1..].copy_from_slice(&payload);
    Frame::new(MASTER_ID, &d).unwrap_or_else(|_| unreachable!("8 bytes"))
}

fn response(command: u8, payload: [u8; 7]) -> Frame {
    let mut d = [0u8; 8];
    d[0] = command;
    d[1..].copy_from_slice(&payload);
    Frame::new(SLAVE_ID, &d).unwrap_or_else(|_| unreachable!("8 bytes"))
}

fn u32_payload(v: u32) -> [u8; 7] {
    let b = v.to_le_bytes();
    [b[0], b[1], b[2], b[3], 0, 0, 0]
}

/// The LSS states of a slave.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LssState {
    /// Normal operation; only switch-state and identification services are answered.
    Waiting,
    /// Accepts configuration.
    Configuration,
}

/// What the application must do after an LSS request.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LssAction {
    /// Persist the pending node-ID and bit timing (answer with [`LssSlave::store_result`]).
    Store,
    /// Switch to the pending bit timing after `delay_ms`, and wait as long again before sending.
    ActivateBitTiming {
        /// The switch delay in ms.
        delay_ms: u16,
    },
    /// The state changed; entering waiting with a new pending node-ID means: apply it (CiA 305:
    /// at the next reset communication, or at once if the node had none).
    StateChanged(LssState),
}

/// The LSS slave of one node.
#[derive(Debug, Clone)]
pub struct LssSlave {
    address: [u32; 4],
    state: LssState,
    active_node_id: u8,
    pending_node_id: u8,
    pending_bit_timing: Option<u8>,
    /// Bits of a selective switch matched so far.
    selective: u8,
    /// Fastscan: which part of the address is being scanned.
    fastscan_pos: u8,
}

impl LssSlave {
    /// A slave with LSS address `address` (0x1018 sub 1–4) and node-ID (0xFF: none).
    pub fn new(address: [u32; 4], node_id: u8) -> Self {
        LssSlave {
            address,
            state: LssState::Waiting,
            active_node_id: node_id,
            pending_node_id: node_id,
            pending_bit_timing: None,
            selective: 0,
            fastscan_pos: 0,
        }
    }

    /// The LSS state.
    pub fn state(&self) -> LssState {
        self.state
    }

    /// The node-ID configured by LSS, to apply at the next reset communication.
    pub fn pending_node_id(&self) -> u8 {
        self.pending_node_id
    }

    /// The bit timing index configured by LSS, if any.
    pub fn pending_bit_timing(&self) -> Option<u8> {
        self.pending_bit_timing
    }

    /// The node-ID in use (after a reset communication applied the pending one).
    pub fn set_active_node_id(&mut self, id: u8) {
        self.active_node_id = id;
    }

    /// Answer a store request: 0 success, 1 not supported, 2 storage access error.
    pub fn store_result(&self, error: u8, out: &mut Vec<Frame>) {
        out.push(response(cs::STORE, [error, 0, 0, 0, 0, 0, 0]));
    }

    fn enter(&mut self, state: LssState, action: &mut Option<LssAction>) {
        if self.state != state {
            self.state = state;
            *action = Some(LssAction::StateChanged(state));
        }
    }

    /// Handle a frame on 0x7E5: its response goes to `out`; returns what the application must
    /// do.
    pub fn handle(&mut self, frame: &Frame, out: &mut Vec<Frame>) -> Option<LssAction> {
        let mut action = None;
        let Ok(d): Result<[u8; 8], _> = frame.data().try_into() else {
            return None;
        };
        if frame.id() != MASTER_ID {
            return None;
        }
        let value = u32::from_le_bytes([d[1], d[2], d[3], d[4]]);
        let configuring = self.state == LssState::Configuration;
        let reply = match d[0] {
            cs::SWITCH_GLOBAL => {
                match d[1] {
                    0 => self.enter(LssState::Waiting, &mut action),
                    1 => self.enter(LssState::Configuration, &mut action),
                    _ => {}
                }
                None
            }
            c @ cs::SWITCH_SELECTIVE_VENDOR..=cs::SWITCH_SELECTIVE_SERIAL => {
                let part = usize::from(c - cs::SWITCH_SELECTIVE_VENDOR);
                if self.address[part] == value && (part == 0 || self.selective == part as u8) {
                    self.selective = part as u8 + 1;
                } else {
                    self.selective = 0;
                }
                if self.selective == 4 {
                    self.selective = 0;
                    self.enter(LssState::Configuration, &mut action);
                    Some(response(cs::SWITCH_SELECTIVE_RESPONSE, [0; 7]))
                } else {
                    None
                }
            }
            cs::CONFIGURE_NODE_ID if configuring => {
                let ok = (1..=127).contains(&d[1]) || d[1] == UNCONFIGURED;
                if ok {
                    self.pending_node_id = d[1];
                }
                Some(response(
                    cs::CONFIGURE_NODE_ID,
                    [u8::from(!ok), 0, 0, 0, 0, 0, 0],
                ))
            }
            cs::CONFIGURE_BIT_TIMING if configuring => {
                let ok = d[1] == 0
                    && BIT_TIMINGS
                        .get(usize::from(d[2]))
                        .is_some_and(Option::is_some);
                if ok {
                    self.pending_bit_timing = Some(d[2]);
                }
                Some(response(
                    cs::CONFIGURE_BIT_TIMING,
                    [u8::from(!ok), 0, 0, 0, 0, 0, 0],
                ))
            }
            cs::ACTIVATE_BIT_TIMING if configuring => {
                action = Some(LssAction::ActivateBitTiming {
                    delay_ms: u16::from_le_bytes([d[1], d[2]]),
                });
                None
            }
            cs::STORE if configuring => {
                action = Some(LssAction::Store);
                None
            }
            c @ cs::INQUIRE_VENDOR..=cs::INQUIRE_SERIAL if configuring => Some(response(
                c,
                u32_payload(self.address[usize::from(c - cs::INQUIRE_VENDOR)]),
            )),
            cs::INQUIRE_NODE_ID if configuring => Some(response(
                cs::INQUIRE_NODE_ID,
                [self.active_node_id, 0, 0, 0, 0, 0, 0],
            )),
            c @ cs::IDENTIFY_VENDOR..=cs::IDENTIFY_SERIAL_HIGH => self.identify(c, value),
            cs::IDENTIFY_NON_CONFIGURED if self.active_node_id == UNCONFIGURED => {
                Some(response(cs::IDENTIFY_NON_CONFIGURED_RESPONSE, [0; 7]))
            }
            cs::FASTSCAN => self.fastscan(value, d[5], d[6], d[7], &mut action),
            _ => None,
        };
        out.extend(reply);
        action
    }

    /// Identify remote slave: vendor and product must match, revision and serial lie within
    /// the ranges the master sends (low then high); the slave answers after the serial high.
    fn identify(&mut self, c: u8, value: u32) -> Option<Frame> {
        let step = c - cs::IDENTIFY_VENDOR; // 0 vendor, 1 product, 2 rev low, 3 rev high, 4 serial low, 5 serial high
        let ok = match step {
            0 => self.address[0] == value,
            1 => self.address[1] == value,
            2 => self.address[2] >= value,
            3 => self.address[2] <= value,
            4 => self.address[3] >= value,
            _ => self.address[3] <= value,
        };
        self.selective = if ok && (step == 0 || self.selective == step) {
            step + 1
        } else {
            0
        };
        if self.selective == 6 {
            self.selective = 0;
            return Some(response(cs::IDENTIFY_RESPONSE, [0; 7]));
        }
        None
    }

    /// Fastscan (CiA 305 §6.7): slaves without a node-ID, in the waiting state, answer while the
    /// checked bits of the current address part match; a fully matched last part puts the slave
    /// into configuration.
    fn fastscan(
        &mut self,
        id: u32,
        bit_checked: u8,
        sub: u8,
        next: u8,
        action: &mut Option<LssAction>,
    ) -> Option<Frame> {
        if self.state != LssState::Waiting || self.active_node_id != UNCONFIGURED {
            return None;
        }
        if bit_checked == 0x80 {
            self.fastscan_pos = 0;
            return Some(response(cs::IDENTIFY_RESPONSE, [0; 7]));
        }
        if bit_checked > 31 || sub > 3 || next > 3 || sub != self.fastscan_pos {
            return None;
        }
        let mask = u32::MAX << bit_checked;
        if (self.address[usize::from(sub)] ^ id) & mask != 0 {
            return None;
        }
        if bit_checked == 0 {
            self.fastscan_pos = next;
            if sub == 3 && next == 0 {
                self.enter(LssState::Configuration, action);
            }
        }
        Some(response(cs::IDENTIFY_RESPONSE, [0; 7]))
    }
}

/// The next Fastscan request of a master scanning bit `bit` of part `sub` with the bits known
/// so far in `id`: the bit is assumed 0; silence means it is 1.
pub fn fastscan_request(id: u32, bit_checked: u8, sub: u8, next: u8) -> Frame {
    let b = id.to_le_bytes();
    request(
        cs::FASTSCAN,
        [b[0], b[1], b[2], b[3], bit_checked, sub, next],
    )
}

/// What a Fastscan master does with one part of the LSS address (CiA 305 §6.7; the scan types
/// of CiA 309-3's `lss_allnodes`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FastscanPart {
    /// Find it bit by bit (32 steps and a confirmation).
    #[default]
    Scan,
    /// Leave it out: the slaves' value is not checked (reported as 0). Only the product code
    /// and the revision can be left out: a slave starts at the vendor-ID and is selected by the
    /// serial number's confirmation.
    Skip,
    /// Only slaves with this value (one confirmation step).
    Match(u32),
}

/// Why a Fastscan cannot be run as asked.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("Fastscan cannot skip the vendor-ID or the serial number")]
pub struct FastscanSkipError;

/// Where a Fastscan master stands.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum FastscanStep {
    /// Is any unconfigured slave there at all (bit-checked 0x80)?
    Reset,
    /// Checking bit `bit` of part `sub` (the bit assumed 0; silence means 1).
    Bit { sub: u8, bit: u8 },
    /// Confirming the whole part `sub` and moving the slaves on to the next part.
    Confirm { sub: u8 },
}

/// What the master learned from one step.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FastscanProgress {
    /// Send [`FastscanMaster::request`] again after the step time.
    Continue,
    /// A slave is in configuration state with this address (skipped parts 0).
    Found([u32; 4]),
    /// No unconfigured slave (or none matching) answered.
    NotFound,
}

/// The master's side of Fastscan, sans-IO: send [`Self::request`], wait one step time, tell
/// [`Self::answered`] whether any slave answered, until it says found or not found.
#[derive(Debug, Clone)]
pub struct FastscanMaster {
    parts: [FastscanPart; 4],
    address: [u32; 4],
    step: FastscanStep,
}

impl FastscanMaster {
    /// A scan treating each address part as `parts` says.
    pub fn new(parts: [FastscanPart; 4]) -> Result<Self, FastscanSkipError> {
        if parts[0] == FastscanPart::Skip || parts[3] == FastscanPart::Skip {
            return Err(FastscanSkipError);
        }
        Ok(FastscanMaster {
            parts,
            address: [0; 4],
            step: FastscanStep::Reset,
        })
    }

    /// The first part after `sub` that is not skipped (0 after the serial number).
    fn next_part(&self, sub: u8) -> u8 {
        (sub + 1..4)
            .find(|&s| self.parts[usize::from(s)] != FastscanPart::Skip)
            .unwrap_or(0)
    }

    /// The frame to send now.
    pub fn request(&self) -> Frame {
        match self.step {
            FastscanStep::Reset => fastscan_request(0, 0x80, 0, 0),
            FastscanStep::Bit { sub, bit } => {
                fastscan_request(self.address[usize::from(sub)], bit, sub, sub)
            }
            FastscanStep::Confirm { sub } => {
                fastscan_request(self.address[usize::from(sub)], 0, sub, self.next_part(sub))
            }
        }
    }

    /// Begin part `sub`: scan it, or confirm the value to match.
    fn start(&mut self, sub: u8) -> FastscanStep {
        match self.parts[usize::from(sub)] {
            FastscanPart::Match(value) => {
                self.address[usize::from(sub)] = value;
                FastscanStep::Confirm { sub }
            }
            FastscanPart::Scan | FastscanPart::Skip => FastscanStep::Bit { sub, bit: 31 },
        }
    }

    /// Whether any slave answered the last request within the step time.
    pub fn answered(&mut self, answered: bool) -> FastscanProgress {
        self.step = match self.step {
            FastscanStep::Reset if answered => self.start(0),
            FastscanStep::Bit { sub, bit } => {
                if !answered {
                    self.address[usize::from(sub)] |= 1 << bit;
                }
                match bit.checked_sub(1) {
                    Some(bit) => FastscanStep::Bit { sub, bit },
                    None => FastscanStep::Confirm { sub },
                }
            }
            FastscanStep::Confirm { sub } if answered => match self.next_part(sub) {
                0 => return FastscanProgress::Found(self.address),
                next => self.start(next),
            },
            FastscanStep::Reset | FastscanStep::Confirm { .. } => {
                return FastscanProgress::NotFound
            }
        };
        FastscanProgress::Continue
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The reply and the action of one frame.
    trait Ask {
        fn ask(&mut self, frame: &Frame) -> (Option<Frame>, Option<LssAction>);
    }

    impl Ask for LssSlave {
        fn ask(&mut self, frame: &Frame) -> (Option<Frame>, Option<LssAction>) {
            let mut out = Vec::new();
            let action = self.handle(frame, &mut out);
            (out.pop(), action)
        }
    }

    const ADDRESS: [u32; 4] = [0x0000_041A, 0x0000_1000, 0x0001_0002, 0x1234_5678];

    fn code(f: &Frame) -> u8 {
        f.data()[0]
    }

    #[test]
    fn selective_switch_configure_inquire_store() {
        let mut s = LssSlave::new(ADDRESS, 5);
        // Configuration services are ignored while waiting.
        assert_eq!(
            s.ask(&request(cs::CONFIGURE_NODE_ID, [9, 0, 0, 0, 0, 0, 0]))
                .0,
            None
        );
        for (i, v) in ADDRESS.iter().enumerate() {
            let (reply, action) = s.ask(&request(
                cs::SWITCH_SELECTIVE_VENDOR + i as u8,
                u32_payload(*v),
            ));
            if i < 3 {
                assert_eq!((reply, action), (None, None));
            } else {
                assert_eq!(code(&reply.unwrap()), cs::SWITCH_SELECTIVE_RESPONSE);
                assert_eq!(
                    action,
                    Some(LssAction::StateChanged(LssState::Configuration))
                );
            }
        }
        let (reply, _) = s.ask(&request(cs::CONFIGURE_NODE_ID, [0x80, 0, 0, 0, 0, 0, 0]));
        assert_eq!(reply.unwrap().data()[1], 1, "node-ID out of range");
        let (reply, _) = s.ask(&request(cs::CONFIGURE_NODE_ID, [9, 0, 0, 0, 0, 0, 0]));
        assert_eq!(reply.unwrap().data()[1], 0);
        assert_eq!(s.pending_node_id(), 9);
        let (reply, _) = s.ask(&request(cs::CONFIGURE_BIT_TIMING, [0, 3, 0, 0, 0, 0, 0]));
        assert_eq!(reply.unwrap().data()[1], 0);
        assert_eq!(s.pending_bit_timing(), Some(3));
        let (reply, _) = s.ask(&request(cs::CONFIGURE_BIT_TIMING, [0, 5, 0, 0, 0, 0, 0]));
        assert_eq!(reply.unwrap().data()[1], 1, "index 5 is reserved");
        let (reply, _) = s.ask(&request(cs::INQUIRE_SERIAL, [0; 7]));
        assert_eq!(reply.unwrap().data()[1..5], 0x1234_5678u32.to_le_bytes());
        let (reply, _) = s.ask(&request(cs::INQUIRE_NODE_ID, [0; 7]));
        assert_eq!(
            reply.unwrap().data()[1],
            5,
            "the active node-ID until reset communication"
        );
        assert_eq!(
            s.ask(&request(cs::STORE, [0; 7])),
            (None, Some(LssAction::Store))
        );
        assert_eq!(
            s.ask(&request(cs::ACTIVATE_BIT_TIMING, [100, 0, 0, 0, 0, 0, 0]))
                .1,
            Some(LssAction::ActivateBitTiming { delay_ms: 100 })
        );
        assert_eq!(
            s.ask(&request(cs::SWITCH_GLOBAL, [0; 7])).1,
            Some(LssAction::StateChanged(LssState::Waiting))
        );
        // A wrong serial number does not select the slave.
        let mut other = LssSlave::new(ADDRESS, 5);
        for (i, v) in ADDRESS.iter().enumerate() {
            let v = if i == 3 { v + 1 } else { *v };
            assert_eq!(
                other
                    .ask(&request(
                        cs::SWITCH_SELECTIVE_VENDOR + i as u8,
                        u32_payload(v)
                    ))
                    .0,
                None
            );
        }
        assert_eq!(other.state(), LssState::Waiting);
    }

    /// [`FastscanMaster`] against a set of slaves on a simulated bus.
    fn fastscan_with(slaves: &mut [LssSlave], parts: [FastscanPart; 4]) -> Option<[u32; 4]> {
        let mut master = FastscanMaster::new(parts).unwrap();
        loop {
            let request = master.request();
            let answered = slaves.iter_mut().filter_map(|s| s.ask(&request).0).count() > 0;
            match master.answered(answered) {
                FastscanProgress::Continue => {}
                FastscanProgress::Found(address) => return Some(address),
                FastscanProgress::NotFound => return None,
            }
        }
    }

    fn fastscan(slaves: &mut [LssSlave]) -> Option<[u32; 4]> {
        fastscan_with(slaves, [FastscanPart::Scan; 4])
    }

    #[test]
    fn fastscan_matches_and_skips_parts() {
        let other = [0x0000_041A, 0x0000_2000, 0x0003_0000, 0x0000_0001];
        let mut slaves = vec![
            LssSlave::new(ADDRESS, UNCONFIGURED),
            LssSlave::new(other, UNCONFIGURED),
        ];
        let product = FastscanPart::Match(other[1]);
        let parts = [
            FastscanPart::Scan,
            product,
            FastscanPart::Skip,
            FastscanPart::Scan,
        ];
        let found = fastscan_with(&mut slaves, parts).unwrap();
        assert_eq!(found, [other[0], other[1], 0, other[3]], "revision skipped");
        assert_eq!(slaves[1].state(), LssState::Configuration);
        assert_eq!(slaves[0].state(), LssState::Waiting);
        slaves[1].set_active_node_id(7);
        slaves[1].ask(&request(cs::SWITCH_GLOBAL, [0; 7]));
        assert_eq!(
            fastscan_with(&mut slaves, parts),
            None,
            "no other of that product"
        );
        let vendor = [
            FastscanPart::Match(ADDRESS[0]),
            FastscanPart::Scan,
            FastscanPart::Scan,
            FastscanPart::Match(ADDRESS[3]),
        ];
        assert_eq!(fastscan_with(&mut slaves, vendor), Some(ADDRESS));
        let skip = FastscanPart::Skip;
        assert!(FastscanMaster::new([
            skip,
            FastscanPart::Scan,
            FastscanPart::Scan,
            FastscanPart::Scan
        ])
        .is_err());
        assert!(FastscanMaster::new([
            FastscanPart::Scan,
            FastscanPart::Scan,
            FastscanPart::Scan,
            skip
        ])
        .is_err());
    }

    #[test]
    fn fastscan_finds_unconfigured_slaves_one_by_one() {
        let second = [0x0000_041A, 0x0000_1000, 0x0001_0002, 0x1234_5679];
        let mut slaves = vec![
            LssSlave::new(ADDRESS, UNCONFIGURED),
            LssSlave::new(second, UNCONFIGURED),
            LssSlave::new([9, 9, 9, 9], 3), // configured: never answers
        ];
        let found = fastscan(&mut slaves).unwrap();
        assert_eq!(found, ADDRESS, "the lowest address wins");
        assert_eq!(slaves[0].state(), LssState::Configuration);
        // Give it a node-ID and put it back to waiting: the next scan finds the other one.
        slaves[0].ask(&request(cs::CONFIGURE_NODE_ID, [20, 0, 0, 0, 0, 0, 0]));
        slaves[0].set_active_node_id(20);
        slaves[0].ask(&request(cs::SWITCH_GLOBAL, [0; 7]));
        assert_eq!(fastscan(&mut slaves).unwrap(), second);
        slaves[1].set_active_node_id(21);
        slaves[1].ask(&request(cs::SWITCH_GLOBAL, [0; 7]));
        assert_eq!(fastscan(&mut slaves), None, "nobody left");
    }

    #[test]
    fn identify_remote_slave_by_ranges() {
        let mut s = LssSlave::new(ADDRESS, 5);
        let steps = [
            0x41A,
            0x1000,
            0x0001_0000,
            0x0001_FFFF,
            0x1000_0000,
            0x2000_0000,
        ];
        let mut last = None;
        for (i, v) in steps.iter().enumerate() {
            last = s
                .ask(&request(cs::IDENTIFY_VENDOR + i as u8, u32_payload(*v)))
                .0;
        }
        assert_eq!(code(&last.unwrap()), cs::IDENTIFY_RESPONSE);
        let (reply, _) = s.ask(&request(cs::IDENTIFY_NON_CONFIGURED, [0; 7]));
        assert_eq!(reply, None, "has a node-ID");
    }
}
