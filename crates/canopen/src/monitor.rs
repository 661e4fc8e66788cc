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
use crate::od::ObjectDictionary;
use crate::sdo::abort::AbortCode;
use crate::time::TimeOfDay;
use crate::types::{civil_from_days, DataType, Value, CANOPEN_EPOCH_DAYS};

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

/// A whole SDO transfer seen on the bus.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SdoTransfer {
    /// The server's node-ID.
    pub node: u8,
    /// Upload (read) or download (write).
    pub upload: bool,
    /// Object index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// The data, or the abort code that ended the transfer.
    pub result: Result<Vec<u8>, AbortCode>,
    /// Expedited, segmented or block.
    pub protocol: &'static str,
}

impl fmt::Display for SdoTransfer {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let dir = if self.upload { "read" } else { "write" };
        write!(
            f,
            "SDO {dir} node {} {:04X}:{:02X} ({})",
            self.node, self.index, self.sub, self.protocol
        )?;
        match &self.result {
            Err(code) => write!(f, " ABORTED {code}"),
            Ok(data) => {
                write!(f, " {} bytes", data.len())?;
                let shown = &data[..data.len().min(16)];
                if !shown.is_empty() {
                    write!(f, ": {}", hex(shown))?;
                    if data.len() > shown.len() {
                        write!(f, " …")?;
                    }
                }
                if data.len() > 4 && data.iter().all(|b| (0x20..0x7F).contains(b)) {
                    write!(f, " \"{}\"", String::from_utf8_lossy(data))?;
                }
                Ok(())
            }
        }
    }
}

#[derive(Debug, Default)]
struct Transfer {
    upload: bool,
    index: u16,
    sub: u8,
    data: Vec<u8>,
    protocol: &'static str,
    /// Block transfers: bytes received in the current sub-block, in sequence.
    block_data: Vec<u8>,
    expected_seq: u8,
    /// Set when the data is complete; reported when the other side confirms.
    complete: bool,
}

/// Reassembles whole SDO transfers from the frames of the default channels (0x600/0x580 +
/// node-ID), for bus monitors. Feed every frame; complete and aborted transfers come out.
#[derive(Debug, Default)]
pub struct SdoTracker {
    transfers: std::collections::HashMap<u8, Transfer>,
}

impl SdoTracker {
    /// A tracker with nothing in progress.
    pub fn new() -> Self {
        Self::default()
    }

    /// Take one frame; returns a transfer that this frame finished.
    pub fn feed(&mut self, frame: &Frame) -> Option<SdoTransfer> {
        let (request, node) = match classify(match frame.id() {
            CanId::Standard(id) => id,
            CanId::Extended(_) => return None,
        }) {
            Function::SdoRequest(n) => (true, n),
            Function::SdoResponse(n) => (false, n),
            _ => return None,
        };
        let d: &[u8; 8] = frame.data().try_into().ok()?;
        let finish = |t: Transfer, result: Result<Vec<u8>, AbortCode>| SdoTransfer {
            node,
            upload: t.upload,
            index: t.index,
            sub: t.sub,
            result,
            protocol: t.protocol,
        };
        // Inside a block sub-block, frames of the sending side are segments.
        if let Some(t) = self.transfers.get_mut(&node) {
            let sending_side = if t.upload { !request } else { request };
            if t.protocol == "block" && sending_side && !t.complete && d[0] != 0x80 {
                let seq = d[0] & 0x7F;
                if seq == t.expected_seq {
                    t.block_data.extend_from_slice(&d[1..8]);
                    t.expected_seq += 1;
                    if d[0] & 0x80 != 0 {
                        t.complete = true;
                    }
                }
                return None;
            }
        }
        if d[0] == 0x80
            || (d[0] >> 5 == 4
                && !self
                    .transfers
                    .get(&node)
                    .is_some_and(|t| t.protocol == "block" && !t.complete))
        {
            let t = self.transfers.remove(&node)?;
            return Some(finish(t, Err(AbortCode(u32_at(d, 4)))));
        }
        let (index, sub) = (u16_at(d, 1), d[3]);
        let cs = d[0] >> 5;
        match (request, cs) {
            // Initiate download.
            (true, 1) => {
                let expedited = d[0] & 2 != 0;
                let n = if expedited && d[0] & 1 != 0 {
                    usize::from((d[0] >> 2) & 3)
                } else {
                    0
                };
                let data = if expedited {
                    d[4..8 - n].to_vec()
                } else {
                    Vec::new()
                };
                self.transfers.insert(
                    node,
                    Transfer {
                        index,
                        sub,
                        data,
                        complete: expedited,
                        protocol: if expedited { "expedited" } else { "segmented" },
                        ..Transfer::default()
                    },
                );
            }
            // Initiate upload / block upload.
            (true, 2) => {
                self.transfers.insert(
                    node,
                    Transfer {
                        upload: true,
                        index,
                        sub,
                        protocol: "segmented",
                        ..Transfer::default()
                    },
                );
            }
            (true, 5) if d[0] & 3 == 0 => {
                self.transfers.insert(
                    node,
                    Transfer {
                        upload: true,
                        index,
                        sub,
                        protocol: "block",
                        expected_seq: 1,
                        ..Transfer::default()
                    },
                );
            }
            (true, 6) if d[0] & 1 == 0 => {
                self.transfers.insert(
                    node,
                    Transfer {
                        index,
                        sub,
                        protocol: "block",
                        expected_seq: 1,
                        ..Transfer::default()
                    },
                );
            }
            // Server answers to an upload initiate.
            (false, 2) => {
                let t = self.transfers.get_mut(&node)?;
                if d[0] & 2 != 0 {
                    let n = if d[0] & 1 != 0 {
                        usize::from((d[0] >> 2) & 3)
                    } else {
                        0
                    };
                    let mut t = self.transfers.remove(&node)?;
                    t.protocol = "expedited";
                    return Some(finish(t, Ok(d[4..8 - n].to_vec())));
                }
                t.protocol = "segmented";
            }
            // Download segments (client) and upload segments (server).
            (true, 0) | (false, 0) => {
                let t = self.transfers.get_mut(&node)?;
                let n = usize::from((d[0] >> 1) & 7);
                t.data.extend_from_slice(&d[1..8 - n]);
                if d[0] & 1 != 0 {
                    t.complete = true;
                    if !request {
                        let t = self.transfers.remove(&node)?;
                        let data = t.data.clone();
                        return Some(finish(t, Ok(data)));
                    }
                }
            }
            // Server confirms a download (initiate or segment).
            (false, 3) | (false, 1)
                if self
                    .transfers
                    .get(&node)
                    .is_some_and(|t| t.complete && !t.upload) =>
            {
                let t = self.transfers.remove(&node)?;
                let data = t.data.clone();
                return Some(finish(t, Ok(data)));
            }
            // Block acknowledgements: keep what was acknowledged, drop the rest of the sub-block.
            (false, 5) | (true, 5) if d[0] & 3 == 2 => {
                let t = self.transfers.get_mut(&node)?;
                let keep = (usize::from(d[1]) * 7).min(t.block_data.len());
                let acked: Vec<u8> = t.block_data.drain(..).take(keep).collect();
                t.data.extend_from_slice(&acked);
                if usize::from(d[1]) < usize::from(t.expected_seq.saturating_sub(1)) {
                    t.complete = false;
                }
                t.expected_seq = 1;
            }
            // Block end (download: client; upload: server) carries the unused byte count.
            (true, 6) | (false, 6) if d[0] & 1 == 1 => {
                let t = self.transfers.get_mut(&node)?;
                let n = usize::from((d[0] >> 2) & 7);
                let keep = t.data.len().saturating_sub(n);
                t.data.truncate(keep);
                t.complete = true;
            }
            // Block end confirmations.
            (false, 5) | (true, 5) if d[0] & 3 == 1 => {
                let t = self.transfers.remove(&node)?;
                let data = t.data.clone();
                return Some(finish(t, Ok(data)));
            }
            _ => {}
        }
        None
    }
}

#[cfg(test)]
mod tracker_tests {
    use super::*;
    use crate::od::{Access, Object, ObjectDictionary, Variable};
    use crate::sdo::client::{ClientConfig, SdoClient, Transfer as How};
    use crate::sdo::server::{SdoServer, ServerConfig};
    use crate::types::{DataType, Value};
    use std::time::Instant;

    /// Run a real client/server transfer and feed every frame to the tracker.
    fn observe(how: How, upload: bool, data: &[u8], lose: Option<usize>) -> Vec<SdoTransfer> {
        let mut od = ObjectDictionary::new();
        od.insert(Object::var(
            0x2000,
            Variable::new("Blob", DataType::Domain, Access::Rw),
        ));
        od.insert(Object::var(
            0x1008,
            Variable::new("Name", DataType::VisibleString, Access::Ro)
                .with_value(Value::Text("x".into())),
        ));
        if upload {
            od.write(0x2000, 0, data).unwrap();
        }
        let now = Instant::now();
        let mut client = SdoClient::new(ClientConfig {
            block_size: 4,
            switch_threshold: 0,
            ..Default::default()
        });
        let mut server = SdoServer::new(ServerConfig {
            block_size: 4,
            ..Default::default()
        });
        let mut tracker = SdoTracker::new();
        let mut seen = Vec::new();
        let mut to_server = Vec::new();
        if upload {
            client
                .start_upload(0x2000, 0, how, now, &mut to_server)
                .unwrap();
        } else {
            client
                .start_download(0x2000, 0, data.to_vec(), how, now, &mut to_server)
                .unwrap();
        }
        let mut count = 0;
        for _ in 0..10_000 {
            let mut to_client = Vec::new();
            for p in to_server.drain(..) {
                count += 1;
                seen.extend(tracker.feed(&Frame::standard(0x605, &p).unwrap()));
                if lose != Some(count) {
                    server.handle(&mut od, &p, now, &mut to_client);
                }
            }
            let mut done = false;
            for p in to_client {
                seen.extend(tracker.feed(&Frame::standard(0x585, &p).unwrap()));
                done |= client.handle(&p, now, &mut to_server).is_some();
            }
            if done {
                for p in to_server.drain(..) {
                    seen.extend(tracker.feed(&Frame::standard(0x605, &p).unwrap()));
                    server.handle(&mut od, &p, now, &mut Vec::new());
                }
                break;
            }
        }
        seen
    }

    #[test]
    fn whole_transfers_are_reassembled() {
        let data: Vec<u8> = (0..100u8).collect();
        for how in [How::Normal, How::Segmented, How::Block] {
            for upload in [true, false] {
                for len in [1usize, 4, 7, 13, 100] {
                    let got = observe(how, upload, &data[..len], None);
                    assert_eq!(got.len(), 1, "{how:?} upload={upload} {len}: {got:?}");
                    assert_eq!(
                        got[0].result,
                        Ok(data[..len].to_vec()),
                        "{how:?} upload={upload} {len}"
                    );
                    assert_eq!(
                        (got[0].index, got[0].sub, got[0].upload, got[0].node),
                        (0x2000, 0, upload, 5)
                    );
                }
            }
        }
        // A lost segment in a block download is repeated: the tracker keeps only acknowledged data.
        let got = observe(How::Block, false, &data, Some(3));
        assert_eq!(got[0].result, Ok(data.clone()));
        let text = got[0].to_string();
        assert!(
            text.starts_with("SDO write node 5 2000:00 (block) 100 bytes: 00 01 02"),
            "{text}"
        );
    }

    #[test]
    fn aborts_are_reported() {
        let mut tracker = SdoTracker::new();
        assert_eq!(
            tracker.feed(&Frame::standard(0x601, &[0x40, 0x00, 0x30, 0, 0, 0, 0, 0]).unwrap()),
            None
        );
        let t = tracker
            .feed(&Frame::standard(0x581, &[0x80, 0x00, 0x30, 0, 0, 0, 2, 6]).unwrap())
            .unwrap();
        assert_eq!(t.result, Err(AbortCode::NO_OBJECT));
        assert!(t.to_string().contains("ABORTED 06020000"), "{t}");
    }
}

/// What a PDO carries: its mapped objects in order, with types where known.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PdoLayout {
    /// `TPDO1 node 1` and the like.
    pub name: String,
    /// Index, sub-index, length in bytes, and the data type when a dictionary tells it.
    pub entries: Vec<(u16, u8, usize, Option<DataType>)>,
}

/// The layouts of the valid TPDOs and RPDOs configured in `od` (an EDS/DCF of node `node`, or
/// a dictionary read back over SDO).
pub fn pdo_layouts(od: &ObjectDictionary, node: u8) -> Vec<(CanId, PdoLayout)> {
    let mut out = Vec::new();
    for (comm, map, kind) in [
        (crate::pdo::TPDO_COMM, crate::pdo::TPDO_MAP, "TPDO"),
        (crate::pdo::RPDO_COMM, crate::pdo::RPDO_MAP, "RPDO"),
    ] {
        for n in 0..crate::pdo::MAX_PDOS {
            let Ok(Value::Uint(cob)) = od.get_value(comm + n, 1) else {
                continue;
            };
            let Some(id) = crate::cob::id_from_parameter(cob as u32) else {
                continue;
            };
            let count = match od.get_value(map + n, 0) {
                Ok(Value::Uint(c)) => c as u8,
                _ => 0,
            };
            let entries: Vec<_> = (1..=count)
                .filter_map(|s| match od.get_value(map + n, s) {
                    Ok(Value::Uint(v)) => Some(crate::pdo::MapEntry::from_u32(v as u32)),
                    _ => None,
                })
                .map(|e| {
                    let ty = od.variable(e.index, e.sub).ok().map(|v| v.data_type);
                    (e.index, e.sub, usize::from(e.bits / 8), ty)
                })
                .collect();
            if !entries.is_empty() {
                out.push((
                    id,
                    PdoLayout {
                        name: format!("{kind}{} node {node}", n + 1),
                        entries,
                    },
                ));
            }
        }
    }
    out
}

/// The values in a PDO's data, by its layout: `2000:00=1234 2001:00=7`.
pub fn decode_pdo(layout: &PdoLayout, data: &[u8]) -> String {
    let mut pos = 0;
    let mut parts = Vec::new();
    for (index, sub, len, ty) in &layout.entries {
        let Some(bytes) = data.get(pos..pos + len) else {
            parts.push(format!("{index:04X}:{sub:02X}=<missing>"));
            break;
        };
        pos += len;
        if (1..=7).contains(index) {
            continue; // dummy entry
        }
        let text = match ty.and_then(|t| {
            crate::types::decode(t, bytes)
                .ok()
                .map(|v| crate::types::to_text(t, &v))
        }) {
            Some(text) => text,
            None if *len <= 8 => {
                let mut wide = [0u8; 8];
                wide[..*len].copy_from_slice(bytes);
                u64::from_le_bytes(wide).to_string()
            }
            None => hex(bytes),
        };
        parts.push(format!("{index:04X}:{sub:02X}={text}"));
    }
    format!("{}: {}", layout.name, parts.join(" "))
}

#[cfg(test)]
mod pdo_layout_tests {
    use super::*;

    #[test]
    fn layouts_from_a_dictionary_decode_frames() {
        let mut od = ObjectDictionary::new();
        od.insert(crate::od::Object::var(
            0x2000,
            crate::od::Variable::new("Position", DataType::Integer16, crate::od::Access::Rw)
                .mappable(),
        ));
        crate::pdo::add_pdo_objects(&mut od, 1, 1, 1);
        let entries = [(0x2000, 0, 16), (0x0005, 0, 8), (0x2100, 1, 32)];
        for (i, (index, sub, bits)) in entries.into_iter().enumerate() {
            let entry = crate::pdo::MapEntry { index, sub, bits }.to_u32();
            od.set(crate::pdo::TPDO_MAP, i as u8 + 1, &entry.to_le_bytes())
                .unwrap();
        }
        od.set(crate::pdo::TPDO_MAP, 0, &[3]).unwrap();
        let layouts = pdo_layouts(&od, 1);
        assert_eq!(layouts.len(), 1, "the RPDO has no mapping");
        let (id, layout) = &layouts[0];
        assert_eq!(*id, CanId::Standard(0x181));
        assert_eq!(
            decode_pdo(layout, &[0xFE, 0xFF, 9, 1, 0, 0, 0]),
            "TPDO1 node 1: 2000:00=-2 2100:01=1"
        );
        assert_eq!(decode_pdo(layout, &[1]), "TPDO1 node 1: 2000:00=<missing>");
    }
}

#[cfg(test)]
mod fuzz_tests {
    use super::*;
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
                let _ = lss.handle(&crate::lss::request(f.data().first().copied().unwrap_or(0), [0; 7]));
                let _ = lss.handle(f);
                let _ = guard.handle(f, crate::nmt::NmtState::Operational, now, &mut ev);
                master.handle(f, &mut ev);
                let _ = pdo.handle_frame(&mut od, f, now, &mut pev);
                let _ = pdo.handle_remote(&od, f, now, &mut out);
                heartbeat.handle(f, now, &mut hev);
            }
        }
    }
}
