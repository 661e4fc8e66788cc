//! Service data objects (CiA 301 §7.2.4): the frames as types ([`msg`]), the sans-IO
//! [`server::SdoServer`] and [`client::SdoClient`], expedited, segmented and block transfers
//! in both directions.
//!
//! Both machines take an 8-byte frame payload and the current time, and push the payloads to
//! send into an output vector; [`server::SdoServer::poll_timeout`] /
//! [`client::SdoClient::poll_timeout`] say when to call `handle_timeout`. The COB-IDs are the
//! business of the tasks that run them (feature `tokio`): `serve` runs the server on a bus,
//! `clients` the async client.

pub mod abort;
pub mod client;
#[cfg(feature = "tokio")]
pub mod clients;
pub mod crc;
pub mod msg;
#[cfg(feature = "tokio")]
pub mod serve;
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

/// The acknowledgement of a sub-block (CiA 301 §7.2.4.3.14): a download response or an upload
/// request, by who received it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) struct Ack {
    pub(crate) ackseq: u8,
    pub(crate) blksize: u8,
}

/// What one received segment means.
pub(crate) struct Received<'a> {
    /// In-sequence data to take now (the last segment's data waits for [`SubBlockReceiver::tail`]).
    pub(crate) data: Option<&'a [u8]>,
    /// The acknowledgement to send, when the sub-block ended.
    pub(crate) ack: Option<Ack>,
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

    /// Take one segment.
    pub(crate) fn segment<'a>(
        &mut self,
        segment: msg::BlockSegment<'a>,
    ) -> Result<Received<'a>, AbortCode> {
        let (seq, is_last) = (segment.seq, segment.last);
        if seq == 0 {
            return Err(AbortCode::SEQUENCE);
        }
        let mut data = None;
        if seq == self.expected {
            if is_last {
                let mut held = [0u8; SEGMENT_DATA];
                held.copy_from_slice(segment.data);
                self.last = Some(held);
            } else {
                data = Some(segment.data);
            }
            self.expected += 1;
        }
        let mut ack = None;
        if seq >= self.blksize || is_last {
            ack = Some(Ack {
                ackseq: self.expected - 1,
                blksize: self.blksize,
            });
            self.expected = 1;
        }
        Ok(Received {
            data,
            ack,
            complete: ack.is_some() && self.last.is_some(),
        })
    }

    /// The data of the last segment, given how many of its bytes the end frame says are unused.
    pub(crate) fn tail(&self, unused: u8) -> Vec<u8> {
        let n = usize::from(unused).min(SEGMENT_DATA);
        let held = self.last.unwrap_or([0; SEGMENT_DATA]);
        held[..SEGMENT_DATA - n].to_vec()
    }
}

/// The size to indicate for an upload: none when unknown, too long beyond 4 GiB − 1.
pub(crate) fn size_indication(size: Option<u64>) -> Result<Option<u32>, AbortCode> {
    size.map(|s| u32::try_from(s).map_err(|_| AbortCode::LENGTH_TOO_HIGH))
        .transpose()
}

/// Convert a received frame to a payload; SDO frames are always 8 bytes.
pub fn payload(data: &[u8]) -> Option<Payload> {
    data.try_into().ok()
}

#[cfg(test)]
mod tests;
