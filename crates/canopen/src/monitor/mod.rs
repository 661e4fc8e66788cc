//! What frames mean in CANopen terms, for bus monitors (`canlift dump`).
//!
//! [`decode`] is per frame and stateless: NMT, SYNC, EMCY, TIME, heartbeat/boot-up/guarding,
//! PDO numbers, each SDO request and response by command specifier (CiA 301 §7.2.4.3, read with
//! [`crate::sdo::msg`]), LSS. Frames in the middle of an SDO block transfer carry no command
//! specifier; without the transfer's state they read as whatever their first byte says, so
//! they are marked `?`. [`SdoTracker`] follows whole SDO transfers; [`pdo_layouts`] and
//! [`decode_pdo`] read PDO contents.

mod pdo;
mod sdo;

pub use pdo::{decode_pdo, pdo_layouts, PdoLayout};
pub use sdo::{Protocol, SdoTracker, SdoTransfer};

use std::fmt;

use canbus::{CanId, Frame, FrameKind};

use crate::cob::{classify, Function};
use crate::emcy::EmcyMessage;
use crate::sdo::msg::{Request, Response};
use crate::sdo::Payload;
use crate::time::TimeOfDay;
use crate::types::{civil_from_days, CANOPEN_EPOCH_DAYS};

/// The CANopen meaning of one frame.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Meaning {
    /// NMT node control: command and target node (0 = all).
    Nmt {
        /// Command specifier.
        command: u8,
        /// Target node-ID, 0 for all.
        node: u8,
    },
    /// SYNC, with the counter when 0x1019 is in use.
    Sync(Option<u8>),
    /// Emergency object.
    Emcy {
        /// Producer.
        node: u8,
        /// Emergency error code (0 = error reset).
        code: u16,
        /// Error register 0x1001.
        register: u8,
        /// Manufacturer-specific error field.
        manufacturer: [u8; 5],
    },
    /// TIME: milliseconds after midnight and days since 1984-01-01.
    Time {
        /// Milliseconds after midnight.
        ms: u32,
        /// Days since 1984-01-01.
        days: u16,
    },
    /// A PDO (number 1–4 of the pre-defined set) of a node.
    Pdo {
        /// Transmit (true) or receive PDO.
        transmit: bool,
        /// PDO number 1–4.
        number: u8,
        /// Node-ID.
        node: u8,
    },
    /// SDO client → server (node-ID of the server, the frame).
    SdoRequest(u8, Payload),
    /// SDO server → client.
    SdoResponse(u8, Payload),
    /// Heartbeat or boot-up (state 0) of a node.
    Heartbeat {
        /// Producer.
        node: u8,
        /// NMT state byte (toggle bit cleared).
        state: u8,
        /// Node guarding toggle bit (bit 7), meaningful only for guarding replies.
        toggle: bool,
    },
    /// Node guarding request (RTR on 700h + node).
    GuardRequest(u8),
    /// LSS request (master → slave) or response with its command specifier.
    Lss {
        /// Master to slave.
        request: bool,
        /// Command specifier.
        cs: u8,
    },
    /// Not part of the pre-defined connection set, or malformed for its service.
    Unknown,
}

/// What `frame` means on a CANopen network using the pre-defined connection set.
pub fn decode(frame: &Frame) -> Meaning {
    let CanId::Standard(cob) = frame.id() else {
        return Meaning::Unknown;
    };
    let d = frame.data();
    let remote = frame.kind() == FrameKind::Remote;
    if frame.kind() == FrameKind::Error {
        return Meaning::Unknown;
    }
    match classify(cob) {
        Function::Nmt if d.len() == 2 => Meaning::Nmt {
            command: d[0],
            node: d[1],
        },
        Function::Sync if d.len() <= 1 => Meaning::Sync(d.first().copied()),
        Function::Emcy(node) => match EmcyMessage::parse(d) {
            Some(m) => Meaning::Emcy {
                node,
                code: m.code,
                register: m.register,
                manufacturer: m.manufacturer,
            },
            None => Meaning::Unknown,
        },
        Function::Time => match TimeOfDay::parse(d) {
            Some(t) => Meaning::Time {
                ms: t.ms,
                days: t.days,
            },
            None => Meaning::Unknown,
        },
        Function::Tpdo(number, node) => Meaning::Pdo {
            transmit: true,
            number,
            node,
        },
        Function::Rpdo(number, node) => Meaning::Pdo {
            transmit: false,
            number,
            node,
        },
        Function::SdoRequest(node) => match d.try_into() {
            Ok(p) => Meaning::SdoRequest(node, p),
            Err(_) => Meaning::Unknown,
        },
        Function::SdoResponse(node) => match d.try_into() {
            Ok(p) => Meaning::SdoResponse(node, p),
            Err(_) => Meaning::Unknown,
        },
        Function::ErrorControl(node) if remote => Meaning::GuardRequest(node),
        Function::ErrorControl(node) if d.len() == 1 => Meaning::Heartbeat {
            node,
            state: d[0] & 0x7F,
            toggle: d[0] & 0x80 != 0,
        },
        Function::LssRequest | Function::LssResponse if d.len() == 8 => Meaning::Lss {
            request: cob == 0x7E5,
            cs: d[0],
        },
        _ => Meaning::Unknown,
    }
}

fn nmt_command(cs: u8) -> &'static str {
    match cs {
        0x01 => "Start",
        0x02 => "Stop",
        0x80 => "Enter pre-operational",
        0x81 => "Reset node",
        0x82 => "Reset communication",
        _ => "unknown command",
    }
}

/// The name of an NMT state as heartbeat and guarding report it (CiA 301 §7.2.8.3.2).
pub fn nmt_state_name(state: u8) -> &'static str {
    match state {
        0x00 => "boot-up",
        0x04 => "stopped",
        0x05 => "operational",
        0x7F => "pre-operational",
        _ => "unknown state",
    }
}

/// A frame of no command specifier: block data, which only the transfer's state can tell.
fn unreadable(f: &mut fmt::Formatter<'_>, p: &Payload) -> fmt::Result {
    write!(f, "? command specifier {} (block data?)", p[0] >> 5)
}

pub(crate) fn hex(data: &[u8]) -> String {
    data.iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// What an EMCY code means: (English, German).
pub type EmcyText = fn(u16) -> (&'static str, &'static str);

impl Meaning {
    /// The meaning with EMCY codes explained by `emcy_text` (a profile knows its own codes
    /// beyond the CiA 301 classes [`Meaning`]'s `Display` names).
    pub fn explained(&self, emcy_text: EmcyText) -> Explained<'_> {
        Explained {
            meaning: self,
            emcy_text,
        }
    }
}

/// A [`Meaning`] written with a profile's EMCY texts.
pub struct Explained<'a> {
    meaning: &'a Meaning,
    emcy_text: EmcyText,
}

impl fmt::Display for Meaning {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.explained(crate::emcy::describe).fmt(f)
    }
}

impl fmt::Display for Explained<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.meaning {
            Meaning::Nmt { command, node: 0 } => {
                write!(f, "NMT {} all nodes", nmt_command(*command))
            }
            Meaning::Nmt { command, node } => {
                write!(f, "NMT {} node {node}", nmt_command(*command))
            }
            Meaning::Sync(None) => write!(f, "SYNC"),
            Meaning::Sync(Some(c)) => write!(f, "SYNC counter {c}"),
            Meaning::Emcy {
                node,
                code: 0,
                register,
                ..
            } => write!(f, "EMCY node {node}: error reset, register {register:02X}"),
            Meaning::Emcy {
                node,
                code,
                register,
                manufacturer,
            } => write!(
                f,
                "EMCY node {node}: code {code:04X} {}, register {register:02X}, data {}",
                (self.emcy_text)(*code).0,
                hex(manufacturer)
            ),
            Meaning::Time { ms, days } => {
                let (y, m, d) = civil_from_days(CANOPEN_EPOCH_DAYS + i64::from(*days));
                let (h, min, s, milli) =
                    (ms / 3_600_000, ms / 60_000 % 60, ms / 1000 % 60, ms % 1000);
                write!(
                    f,
                    "TIME {y:04}-{m:02}-{d:02} {h:02}:{min:02}:{s:02}.{milli:03}"
                )
            }
            Meaning::Pdo {
                transmit,
                number,
                node,
            } => {
                let dir = if *transmit { "TPDO" } else { "RPDO" };
                write!(f, "{dir}{number} node {node}")
            }
            Meaning::SdoRequest(node, p) => {
                write!(f, "SDO req  node {node}: ")?;
                match Request::read(p) {
                    Ok(r) => write!(f, "{r}"),
                    Err(_) => unreadable(f, p),
                }
            }
            Meaning::SdoResponse(node, p) => {
                write!(f, "SDO resp node {node}: ")?;
                match Response::read(p) {
                    Ok(r) => write!(f, "{r}"),
                    Err(_) => unreadable(f, p),
                }
            }
            Meaning::Heartbeat { node, state: 0, .. } => write!(f, "Boot-up node {node}"),
            Meaning::Heartbeat { node, state, .. } => {
                write!(f, "Heartbeat node {node}: {}", nmt_state_name(*state))
            }
            Meaning::GuardRequest(node) => write!(f, "Node guarding request node {node}"),
            Meaning::Lss { request: true, cs } => write!(f, "LSS request cs {cs:02X}"),
            Meaning::Lss { request: false, cs } => write!(f, "LSS response cs {cs:02X}"),
            Meaning::Unknown => Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn text(id: u16, data: &[u8]) -> String {
        decode(&Frame::standard(id, data).unwrap()).to_string()
    }

    #[test]
    fn network_services() {
        assert_eq!(text(0x000, &[0x01, 0x00]), "NMT Start all nodes");
        assert_eq!(text(0x000, &[0x81, 0x0C]), "NMT Reset node node 12");
        assert_eq!(text(0x080, &[]), "SYNC");
        assert_eq!(text(0x080, &[7]), "SYNC counter 7");
        assert_eq!(
            text(0x081, &[0x30, 0x81, 0x11, 0, 0x0C, 0, 0, 0]),
            "EMCY node 1: code 8130 Life guard or heartbeat error, register 11, data 00 0C 00 00 00"
        );
        assert_eq!(
            text(0x081, &[0; 8]),
            "EMCY node 1: error reset, register 00"
        );
        assert_eq!(text(0x701, &[0x05]), "Heartbeat node 1: operational");
        assert_eq!(text(0x70C, &[0x00]), "Boot-up node 12");
        assert_eq!(text(0x70C, &[0xFF]), "Heartbeat node 12: pre-operational");
        assert_eq!(text(0x18C, &[1, 2]), "TPDO1 node 12");
        assert_eq!(text(0x501, &[]), "RPDO4 node 1");
        let rtr = Frame::remote(CanId::Standard(0x709), 1).unwrap();
        assert_eq!(decode(&rtr).to_string(), "Node guarding request node 9");
        assert_eq!(
            text(0x7E5, &[0x04, 1, 0, 0, 0, 0, 0, 0]),
            "LSS request cs 04"
        );
        assert_eq!(text(0x123, &[]), "");
        assert_eq!(text(0x080, &[1, 2]), "", "SYNC with two bytes is not SYNC");
    }

    #[test]
    fn time_stamp() {
        // 2024-01-01 = 14610 days after 1984-01-01; 12:34:56.789.
        let ms: u32 = ((12 * 60 + 34) * 60 + 56) * 1000 + 789;
        let mut data = ms.to_le_bytes().to_vec();
        data.extend(14610u16.to_le_bytes());
        assert_eq!(text(0x100, &data), "TIME 2024-01-01 12:34:56.789");
        assert_eq!(
            text(0x100, &[0, 0, 0, 0, 0, 0]),
            "TIME 1984-01-01 00:00:00.000"
        );
    }

    #[test]
    fn sdo_kinds() {
        assert_eq!(
            text(0x601, &[0x40, 0x18, 0x10, 0x01, 0, 0, 0, 0]),
            "SDO req  node 1: upload 1018:01"
        );
        assert_eq!(
            text(0x581, &[0x43, 0x18, 0x10, 0x01, 0x1A, 0x04, 0, 0]),
            "SDO resp node 1: upload 1018:01 = 1A 04 00 00"
        );
        assert_eq!(
            text(0x601, &[0x2F, 0x17, 0x10, 0x00, 0x64, 0, 0, 0]),
            "SDO req  node 1: download 1017:00 = 64"
        );
        assert_eq!(
            text(0x601, &[0x21, 0x08, 0x10, 0x00, 0x0D, 0, 0, 0]),
            "SDO req  node 1: download 1008:00, 13 bytes"
        );
        assert_eq!(
            text(0x601, &[0x00, b'c', b'a', b'n', b'l', b'i', b'f', b't']),
            "SDO req  node 1: segment t=0 63 61 6E 6C 69 66 74"
        );
        assert_eq!(
            text(0x601, &[0x1B, b'x', b'y', 0, 0, 0, 0, 0]),
            "SDO req  node 1: segment t=1 78 79 (last)"
        );
        assert_eq!(
            text(0x581, &[0x20, 0, 0, 0, 0, 0, 0, 0]),
            "SDO resp node 1: segment ack/request t=0"
        );
        assert_eq!(
            text(0x581, &[0x80, 0x00, 0x20, 0x00, 0x00, 0x00, 0x02, 0x06]),
            "SDO resp node 1: ABORT 2000:00 06020000 (Object does not exist in the object dictionary)"
        );
        assert_eq!(
            text(0x601, &[0xC6, 0x00, 0x20, 0x01, 0, 1, 0, 0]),
            "SDO req  node 1: block download initiate 2000:01"
        );
        assert_eq!(
            text(0x581, &[0xA2, 5, 127, 0, 0, 0, 0, 0]),
            "SDO resp node 1: block download sub-block ack"
        );
        assert_eq!(
            text(0x601, &[0xA4, 0x00, 0x20, 0x01, 127, 0, 0, 0]),
            "SDO req  node 1: block upload initiate 2000:01"
        );
        assert_eq!(
            text(0x601, &[0xA3, 0, 0, 0, 0, 0, 0, 0]),
            "SDO req  node 1: block upload start"
        );
        assert_eq!(
            text(0x581, &[0xC6, 0x00, 0x20, 0x01, 200, 0, 0, 0]),
            "SDO resp node 1: block upload initiate 2000:01"
        );
        assert_eq!(
            text(0x601, &[0xE0, 0, 0, 0, 0, 0, 0, 0]),
            "SDO req  node 1: ? command specifier 7 (block data?)"
        );
    }
}

#[cfg(test)]
mod fuzz_tests {
    use super::*;
    use crate::od::ObjectDictionary;
    use proptest::prelude::*;

    fn arb_frame() -> impl Strategy<Value = Frame> {
        let id = prop_oneof![0x580u16..0x680, 0x700u16..0x800, 0u16..0x800];
        (
            id,
            proptest::collection::vec(any::<u8>(), 0..=8),
            any::<bool>(),
        )
            .prop_map(|(id, data, remote)| {
                if remote {
                    Frame::remote(CanId::Standard(id), data.len() as u8).unwrap()
                } else {
                    Frame::standard(id, &data).unwrap()
                }
            })
    }

    proptest! {
        /// Frame-driven machines take anything the bus carries without panicking.
        #[test]
        fn random_frames_never_panic(frames in proptest::collection::vec(arb_frame(), 0..200)) {
            let now = std::time::Instant::now();
            let mut tracker = SdoTracker::new();
            let mut lss = crate::lss::LssSlave::new([1, 2, 3, 4], crate::lss::UNCONFIGURED);
            let mut guard = crate::guarding::GuardingSlave::new(5);
            let mut master = crate::guarding::GuardingMaster::new();
            master.guard(5, std::time::Duration::from_millis(1), 1, now);
            let mut od = ObjectDictionary::new();
            crate::pdo::add_pdo_objects(&mut od, 5, 4, 4);
            let mut pdo = crate::pdo::PdoEngine::configure(&od, now);
            let mut heartbeat = crate::heartbeat::HeartbeatConsumer::new();
            let (mut ev, mut out, mut pev, mut hev) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
            for f in &frames {
                let _ = decode(f).to_string();
                if let Some(t) = tracker.feed(f) {
                    let _ = t.to_string();
                }
                let _ = lss.handle(&crate::lss::request(f.data().first().copied().unwrap_or(0), [0; 7]), &mut out);
                let _ = lss.handle(f, &mut out);
                guard.handle(f, crate::nmt::NmtState::Operational, now, &mut out, &mut ev);
                master.handle(f, &mut ev);
                let _ = pdo.handle_frame(&mut od, f, now, &mut pev);
                let _ = pdo.handle_remote(&od, f, now, &mut out);
                heartbeat.handle(f, now, &mut hev);
            }
        }
    }
}
