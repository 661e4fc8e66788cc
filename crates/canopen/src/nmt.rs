//! Network management (CiA 301 §7.2.8): the NMT slave state machine, NMT commands, and which
//! services run in which state.

use canbus::{CanId, Frame};

/// The NMT states of a node (CiA 301 §7.3.2.2.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NmtState {
    /// Initialising; left by sending the boot-up message.
    Initialising,
    /// SDO, EMCY, SYNC, TIME and error control run; PDOs do not.
    PreOperational,
    /// Everything runs.
    Operational,
    /// Only NMT and error control (heartbeat, guarding) run.
    Stopped,
}

impl NmtState {
    /// The state byte of heartbeat and guarding messages (boot-up is 0x00).
    pub fn code(self) -> u8 {
        match self {
            NmtState::Initialising => 0x00,
            NmtState::Stopped => 0x04,
            NmtState::Operational => 0x05,
            NmtState::PreOperational => 0x7F,
        }
    }

    /// The state for a heartbeat or guarding state byte (toggle bit ignored).
    pub fn from_code(code: u8) -> Option<Self> {
        match code & 0x7F {
            0x00 => Some(NmtState::Initialising),
            0x04 => Some(NmtState::Stopped),
            0x05 => Some(NmtState::Operational),
            0x7F => Some(NmtState::PreOperational),
            _ => None,
        }
    }

    /// Whether SDO, EMCY, SYNC and TIME run in this state.
    pub fn allows_sdo(self) -> bool {
        matches!(self, NmtState::PreOperational | NmtState::Operational)
    }

    /// Whether PDOs run in this state.
    pub fn allows_pdo(self) -> bool {
        self == NmtState::Operational
    }
}

/// NMT node control commands (CiA 301 §7.2.8.3.1).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NmtCommand {
    /// Start remote node → operational.
    Start,
    /// Stop remote node → stopped.
    Stop,
    /// Enter pre-operational.
    EnterPreOperational,
    /// Reset node (application and communication).
    ResetNode,
    /// Reset communication.
    ResetCommunication,
}

impl NmtCommand {
    /// The command specifier.
    pub fn code(self) -> u8 {
        match self {
            NmtCommand::Start => 0x01,
            NmtCommand::Stop => 0x02,
            NmtCommand::EnterPreOperational => 0x80,
            NmtCommand::ResetNode => 0x81,
            NmtCommand::ResetCommunication => 0x82,
        }
    }

    /// The command with specifier `code`.
    pub fn from_code(code: u8) -> Option<Self> {
        [
            NmtCommand::Start,
            NmtCommand::Stop,
            NmtCommand::EnterPreOperational,
            NmtCommand::ResetNode,
            NmtCommand::ResetCommunication,
        ]
        .into_iter()
        .find(|c| c.code() == code)
    }

    /// The NMT frame commanding `node` (0 = all nodes).
    pub fn frame(self, node: u8) -> Frame {
        Frame::new(CanId::Standard(0), &[self.code(), node])
            .unwrap_or_else(|_| unreachable!("two bytes always fit"))
    }

    /// The command and target node of an NMT frame.
    pub fn parse(frame: &Frame) -> Option<(Self, u8)> {
        match (frame.id(), frame.data()) {
            (CanId::Standard(0), [cs, node]) => Some((Self::from_code(*cs)?, *node)),
            _ => None,
        }
    }
}

/// The boot-up message of `node` (heartbeat COB-ID, state byte 0).
pub fn boot_up_frame(node: u8) -> Frame {
    Frame::standard(0x700 + u16::from(node & 0x7F), &[0])
        .unwrap_or_else(|_| unreachable!("0x77F at most"))
}

/// What the application must do after an NMT command.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NmtAction {
    /// The state changed to this one.
    Entered(NmtState),
    /// Reset the application (restore manufacturer and profile parameters from storage), reset
    /// communication, then call [`NmtSlave::boot`].
    ResetNode,
    /// Reset the communication parameters (0x1000–0x1FFF), then call [`NmtSlave::boot`].
    ResetCommunication,
}

/// The NMT slave state machine of one node.
#[derive(Debug, Clone)]
pub struct NmtSlave {
    node_id: u8,
    state: NmtState,
}

impl NmtSlave {
    /// A node that is initialising.
    pub fn new(node_id: u8) -> Self {
        NmtSlave {
            node_id,
            state: NmtState::Initialising,
        }
    }

    /// The node-ID.
    pub fn node_id(&self) -> u8 {
        self.node_id
    }

    /// The current state.
    pub fn state(&self) -> NmtState {
        self.state
    }

    /// Initialisation is complete: enter pre-operational and send the boot-up message.
    pub fn boot(&mut self, out: &mut Vec<Frame>) {
        self.state = NmtState::PreOperational;
        out.push(boot_up_frame(self.node_id));
    }

    /// Handle an NMT frame; `None` when it is not addressed to this node or changes nothing.
    pub fn handle(&mut self, frame: &Frame) -> Option<NmtAction> {
        let (command, target) = NmtCommand::parse(frame)?;
        if target != 0 && target != self.node_id {
            return None;
        }
        if self.state == NmtState::Initialising {
            return None;
        }
        let next = match command {
            NmtCommand::Start => NmtState::Operational,
            NmtCommand::Stop => NmtState::Stopped,
            NmtCommand::EnterPreOperational => NmtState::PreOperational,
            NmtCommand::ResetNode => {
                self.state = NmtState::Initialising;
                return Some(NmtAction::ResetNode);
            }
            NmtCommand::ResetCommunication => {
                self.state = NmtState::Initialising;
                return Some(NmtAction::ResetCommunication);
            }
        };
        (next != self.state).then(|| {
            self.state = next;
            NmtAction::Entered(next)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn state_machine() {
        let mut nmt = NmtSlave::new(5);
        assert_eq!(nmt.state(), NmtState::Initialising);
        assert_eq!(
            nmt.handle(&NmtCommand::Start.frame(0)),
            None,
            "ignored while initialising"
        );
        let mut out = Vec::new();
        nmt.boot(&mut out);
        assert_eq!(out, [Frame::standard(0x705, &[0]).unwrap()]);
        assert_eq!(nmt.state(), NmtState::PreOperational);
        assert_eq!(
            nmt.handle(&NmtCommand::Start.frame(6)),
            None,
            "another node"
        );
        assert_eq!(
            nmt.handle(&NmtCommand::Start.frame(5)),
            Some(NmtAction::Entered(NmtState::Operational))
        );
        assert_eq!(
            nmt.handle(&NmtCommand::Start.frame(0)),
            None,
            "already operational"
        );
        assert_eq!(
            nmt.handle(&NmtCommand::Stop.frame(0)),
            Some(NmtAction::Entered(NmtState::Stopped))
        );
        assert!(!nmt.state().allows_sdo());
        assert_eq!(
            nmt.handle(&NmtCommand::EnterPreOperational.frame(5)),
            Some(NmtAction::Entered(NmtState::PreOperational))
        );
        assert!(nmt.state().allows_sdo() && !nmt.state().allows_pdo());
        assert_eq!(
            nmt.handle(&NmtCommand::ResetCommunication.frame(5)),
            Some(NmtAction::ResetCommunication)
        );
        assert_eq!(nmt.state(), NmtState::Initialising);
        nmt.boot(&mut Vec::new());
        assert_eq!(
            nmt.handle(&NmtCommand::ResetNode.frame(0)),
            Some(NmtAction::ResetNode)
        );
        let bad = Frame::standard(0, &[0x03, 5]).unwrap();
        nmt.boot(&mut Vec::new());
        assert_eq!(nmt.handle(&bad), None, "unknown command specifier");
    }

    #[test]
    fn codes() {
        for s in [
            NmtState::Initialising,
            NmtState::PreOperational,
            NmtState::Operational,
            NmtState::Stopped,
        ] {
            assert_eq!(NmtState::from_code(s.code()), Some(s));
            assert_eq!(
                NmtState::from_code(s.code() | 0x80),
                Some(s),
                "guarding toggle bit"
            );
        }
        assert_eq!(NmtCommand::ResetNode.frame(0).data(), &[0x81, 0]);
        assert_eq!(
            NmtCommand::parse(&Frame::standard(0, &[0x01]).unwrap()),
            None
        );
    }
}
