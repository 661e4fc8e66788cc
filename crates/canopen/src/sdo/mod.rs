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

/// Convert a received frame to a payload; SDO frames are always 8 bytes.
pub fn payload(data: &[u8]) -> Option<Payload> {
    data.try_into().ok()
}

#[cfg(test)]
mod tests;
