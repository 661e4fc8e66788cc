//! Service data objects (CiA 301 §7.2.4): the sans-IO [`server::SdoServer`] and
//! [`client::SdoClient`], expedited, segmented and block transfers in both directions.
//!
//! Both machines take an 8-byte frame payload and the current time, and push the payloads to
//! send into an output vector; [`server::SdoServer::poll_timeout`] /
//! [`client::SdoClient::poll_timeout`] say when to call `handle_timeout`. The COB-IDs are the
//! driver's business.

pub mod abort;
pub mod client;
pub mod crc;
pub mod server;

use std::time::Duration;

use self::abort::AbortCode;

/// One SDO frame payload: always 8 bytes (CiA 301 §7.2.4.3).
pub type Payload = [u8; 8];

/// Data bytes in one segment of a segmented or block transfer.
pub const SEGMENT_DATA: usize = 7;

/// Largest block size (segments per block) CiA 301 allows.
pub const MAX_BLOCK_SIZE: u8 = 127;

/// Default SDO timeout (DESIGN: configurable, 1 s).
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(1);

/// The abort frame for `index`/`sub` with `code` (cs 4).
pub fn abort_payload(index: u16, sub: u8, code: AbortCode) -> Payload {
    let mut p = [0u8; 8];
    p[0] = 0x80;
    p[1..3].copy_from_slice(&index.to_le_bytes());
    p[3] = sub;
    p[4..8].copy_from_slice(&code.0.to_le_bytes());
    p
}

/// An initiate-style frame: command byte, multiplexer, then four data bytes.
pub(crate) fn with_mux(command: u8, index: u16, sub: u8, data: [u8; 4]) -> Payload {
    let mut p = [0u8; 8];
    p[0] = command;
    p[1..3].copy_from_slice(&index.to_le_bytes());
    p[3] = sub;
    p[4..8].copy_from_slice(&data);
    p
}

/// The multiplexer (index, sub-index) of an initiate or abort frame.
pub(crate) fn mux(p: &Payload) -> (u16, u8) {
    (u16::from_le_bytes([p[1], p[2]]), p[3])
}

/// The abort code carried by an abort frame.
pub(crate) fn abort_code(p: &Payload) -> AbortCode {
    AbortCode(u32::from_le_bytes([p[4], p[5], p[6], p[7]]))
}

/// A segment of a block transfer: sequence number, last flag, 7 data bytes.
pub(crate) fn block_segment(seq: u8, last: bool, data: &[u8]) -> Payload {
    let mut p = [0u8; 8];
    p[0] = seq | if last { 0x80 } else { 0 };
    p[1..1 + data.len()].copy_from_slice(data);
    p
}

/// The receiving side of block-transfer sub-blocks: the server in a block download, the client
/// in a block upload (CiA 301 §7.2.4.3.13–14). It takes segments in sequence, ignores the rest
/// of a sub-block after a gap, and acknowledges the last in-sequence segment when the sub-block
/// ends, so the sender repeats from there.
pub(crate) struct SubBlockReceiver {
    blksize: u8,
    expected: u8,
    /// The segment flagged last, held until the end frame says how much of it is data.
    last: Option<[u8; SEGMENT_DATA]>,
}

/// What one received segment means.
pub(crate) struct Received<'a> {
    /// In-sequence data to take now (the last segment's data waits for [`SubBlockReceiver::tail`]).
    pub(crate) data: Option<&'a [u8]>,
    /// The acknowledgement to send, when the sub-block ended.
    pub(crate) ack: Option<Payload>,
    /// The last segment has arrived in sequence: the end frame comes next.
    pub(crate) complete: bool,
}

impl SubBlockReceiver {
    pub(crate) fn new(blksize: u8) -> Self {
        SubBlockReceiver {
            blksize,
            expected: 1,
            last: None,
        }
    }

    /// Take one segment frame.
    pub(crate) fn segment<'a>(&mut self, p: &'a Payload) -> Result<Received<'a>, AbortCode> {
        let seq = p[0] & 0x7F;
        let is_last = p[0] & 0x80 != 0;
        if seq == 0 {
            return Err(AbortCode::SEQUENCE);
        }
        let mut data = None;
        if seq == self.expected {
            if is_last {
                let mut held = [0u8; SEGMENT_DATA];
                held.copy_from_slice(&p[1..8]);
                self.last = Some(held);
            } else {
                data = Some(&p[1..8]);
            }
            self.expected += 1;
        }
        let mut ack = None;
        if seq >= self.blksize || is_last {
            ack = Some([0xA2, self.expected - 1, self.blksize, 0, 0, 0, 0, 0]);
            self.expected = 1;
        }
        Ok(Received {
            data,
            ack,
            complete: ack.is_some() && self.last.is_some(),
        })
    }

    /// The data of the last segment, given the end frame's command byte (n = unused bytes).
    pub(crate) fn tail(&self, end_command: u8) -> Vec<u8> {
        let n = usize::from((end_command >> 2) & 7);
        let held = self.last.unwrap_or([0; SEGMENT_DATA]);
        held[..SEGMENT_DATA - n].to_vec()
    }
}

/// The size field and its flag for an upload response: `(s flag set, bytes)`.
pub(crate) fn size_indication(size: Option<u64>) -> Result<(bool, [u8; 4]), AbortCode> {
    match size {
        Some(s) => {
            let s = u32::try_from(s).map_err(|_| AbortCode::LENGTH_TOO_HIGH)?;
            Ok((true, s.to_le_bytes()))
        }
        None => Ok((false, [0; 4])),
    }
}

/// Convert a received frame to a payload; SDO frames are always 8 bytes.
pub fn payload(data: &[u8]) -> Option<Payload> {
    data.try_into().ok()
}

#[cfg(test)]
mod tests;
