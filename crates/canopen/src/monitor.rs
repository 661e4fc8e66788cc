//! What a single frame means in CANopen terms, for bus monitors (`canlift dump`).
//!
//! Decoding is per frame and stateless: NMT, SYNC, EMCY, TIME, heartbeat/boot-up/guarding,
//! PDO numbers, each SDO request and response by command specifier (CiA 301 §7.2.4.3), LSS.
//! Frames in the middle of an SDO block transfer carry no command specifier; without the
//! transfer's state they read as whatever their first byte says, so they are marked `?`.

use std::fmt;

use canbus::{CanId, Frame, FrameKind};

use crate::cob::{classify, Function};
use crate::emcy::EmcyMessage;
use crate::sdo::abort::AbortCode;
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
    /// SDO client → server.
    SdoRequest(u8, Sdo),
    /// SDO server → client.
    SdoResponse(u8, Sdo),
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

/// One SDO frame by command specifier.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Sdo {
    /// Initiate download request (client) / response (server).
    InitiateDownload {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Expedited data (request only), when present.
        data: Option<Vec<u8>>,
        /// Size indicated for a segmented transfer.
        size: Option<u32>,
    },
    /// Initiate upload request / response.
    InitiateUpload {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Expedited data (response only).
        data: Option<Vec<u8>>,
        /// Size indicated for a segmented transfer.
        size: Option<u32>,
    },
    /// A segment of a segmented transfer (download request, upload response).
    Segment {
        /// Toggle bit.
        toggle: bool,
        /// Last segment.
        last: bool,
        /// Data bytes.
        data: Vec<u8>,
    },
    /// A segment acknowledgement or request carrying only the toggle bit.
    SegmentAck {
        /// Toggle bit.
        toggle: bool,
    },
    /// Block download or upload initiate, sub-block ack, end.
    Block {
        /// Download (true) or upload.
        download: bool,
        /// What step of the block protocol.
        step: &'static str,
        /// Index and sub-index on initiate.
        object: Option<(u16, u8)>,
    },
    /// Abort transfer with its code.
    Abort {
        /// Object index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Abort code.
        code: AbortCode,
    },
    /// Unknown command specifier.
    Invalid(u8),
}

fn u16_at(d: &[u8], at: usize) -> u16 {
    u16::from_le_bytes([d[at], d[at + 1]])
}

fn u32_at(d: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([d[at], d[at + 1], d[at + 2], d[at + 3]])
}

/// Decode the SDO in `d` (8 bytes), from the client (`request`) or from the server.
fn decode_sdo(d: &[u8], request: bool) -> Sdo {
    let cs = d[0] >> 5;
    let object = || (u16_at(d, 1), d[3]);
    // Expedited/size bits of initiate frames: e = bit 1, s = bit 0, n = bits 3..2.
    let expedited = |d: &[u8]| {
        let (e, s) = (d[0] & 2 != 0, d[0] & 1 != 0);
        let n = if s { usize::from((d[0] >> 2) & 3) } else { 0 };
        if e {
            (Some(d[4..8 - n].to_vec()), None)
        } else if s {
            (None, Some(u32_at(d, 4)))
        } else {
            (None, None)
        }
    };
    let segment = |d: &[u8]| Sdo::Segment {
        toggle: d[0] & 0x10 != 0,
        last: d[0] & 1 != 0,
        data: d[1..8 - usize::from((d[0] >> 1) & 7)].to_vec(),
    };
    let ack = |d: &[u8]| Sdo::SegmentAck {
        toggle: d[0] & 0x10 != 0,
    };
    match (request, cs) {
        (_, 4) => Sdo::Abort {
            index: u16_at(d, 1),
            sub: d[3],
            code: AbortCode(u32_at(d, 4)),
        },
        (true, 0) => segment(d),
        (true, 1) => {
            let (data, size) = expedited(d);
            let (index, sub) = object();
            Sdo::InitiateDownload {
                index,
                sub,
                data,
                size,
            }
        }
        (true, 2) => {
            let (index, sub) = object();
            Sdo::InitiateUpload {
                index,
                sub,
                data: None,
                size: None,
            }
        }
        (true, 3) | (false, 1) => ack(d),
        (false, 0) => segment(d),
        (false, 2) => {
            let (data, size) = expedited(d);
            let (index, sub) = object();
            Sdo::InitiateUpload {
                index,
                sub,
                data,
                size,
            }
        }
        (false, 3) => {
            let (index, sub) = object();
            Sdo::InitiateDownload {
                index,
                sub,
                data: None,
                size: None,
            }
        }
        // Block download: client cs 6 (initiate / end), server ss 5 (initiate / ack / end).
        (true, 6) | (false, 5) => {
            let step = match (request, d[0] & 3) {
                (true, s) if s & 1 == 0 => "initiate",
                (true, _) => "end",
                (false, 0) => "initiate",
                (false, 2) => "sub-block ack",
                (false, 1) => "end",
                _ => "?",
            };
            let object = (step == "initiate").then(object);
            Sdo::Block {
                download: true,
                step,
                object,
            }
        }
        // Block upload: client cs 5 (initiate / start / ack / end), server ss 6 (initiate / end).
        (true, 5) | (false, 6) => {
            // The server's initiate response has the size bit in bit 1; only bit 0 is ss.
            let cs = if request { d[0] & 3 } else { d[0] & 1 };
            let step = match (request, cs) {
                (true, 0) | (false, 0) => "initiate",
                (true, 3) => "start",
                (true, 2) => "sub-block ack",
                (true, 1) | (false, 1) => "end",
                _ => "?",
            };
            let object = (step == "initiate").then(object);
            Sdo::Block {
                download: false,
                step,
                object,
            }
        }
        (_, cs) => Sdo::Invalid(cs),
    }
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
        Function::SdoRequest(node) if d.len() == 8 => {
            Meaning::SdoRequest(node, decode_sdo(d, true))
        }
        Function::SdoResponse(node) if d.len() == 8 => {
            Meaning::SdoResponse(node, decode_sdo(d, false))
        }
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

fn hex(data: &[u8]) -> String {
    data.iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

impl fmt::Display for Sdo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let size = |f: &mut fmt::Formatter<'_>, size: &Option<u32>| match size {
            Some(n) => write!(f, ", {n} bytes"),
            None => Ok(()),
        };
        match self {
            Sdo::InitiateDownload {
                index,
                sub,
                data,
                size: n,
            } => {
                write!(f, "download {index:04X}:{sub:02X}")?;
                if let Some(d) = data {
                    write!(f, " = {}", hex(d))?;
                }
                size(f, n)
            }
            Sdo::InitiateUpload {
                index,
                sub,
                data,
                size: n,
            } => {
                write!(f, "upload {index:04X}:{sub:02X}")?;
                if let Some(d) = data {
                    write!(f, " = {}", hex(d))?;
                }
                size(f, n)
            }
            Sdo::Segment { toggle, last, data } => write!(
                f,
                "segment t={} {}{}",
                u8::from(*toggle),
                hex(data),
                if *last { " (last)" } else { "" }
            ),
            Sdo::SegmentAck { toggle } => write!(f, "segment ack/request t={}", u8::from(*toggle)),
            Sdo::Block {
                download,
                step,
                object,
            } => {
                let dir = if *download { "download" } else { "upload" };
                write!(f, "block {dir} {step}")?;
                match object {
                    Some((i, s)) => write!(f, " {i:04X}:{s:02X}"),
                    None => Ok(()),
                }
            }
            Sdo::Abort { index, sub, code } => write!(f, "ABORT {index:04X}:{sub:02X} {code}"),
            Sdo::Invalid(cs) => write!(f, "? command specifier {cs} (block data?)"),
        }
    }
}

impl fmt::Display for Meaning {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
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
                "EMCY node {node}: code {code:04X}, register {register:02X}, data {}",
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
            Meaning::SdoRequest(node, sdo) => write!(f, "SDO req  node {node}: {sdo}"),
            Meaning::SdoResponse(node, sdo) => write!(f, "SDO resp node {node}: {sdo}"),
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
            "EMCY node 1: code 8130, register 11, data 00 0C 00 00 00"
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
