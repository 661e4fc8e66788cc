//! Whole SDO transfers reassembled from the frames of the default channels (0x600/0x580 +
//! node-ID), for bus monitors: expedited, segmented and block, with what a block transfer
//! repeats after a loss counted once.

use std::collections::HashMap;
use std::fmt;

use canbus::{CanId, Frame};

use super::hex;
use crate::cob::{classify, Function};
use crate::sdo::abort::AbortCode;
use crate::sdo::msg::{self, BlockSegment, Initiate, Request, Response};
use crate::sdo::Payload;

/// How a transfer moves its data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Protocol {
    /// In the initiate frames.
    Expedited,
    /// In segments, each confirmed.
    Segmented,
    /// In blocks of segments.
    Block,
}

impl fmt::Display for Protocol {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Protocol::Expedited => "expedited",
            Protocol::Segmented => "segmented",
            Protocol::Block => "block",
        })
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
    pub protocol: Protocol,
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

#[derive(Debug)]
struct Transfer {
    upload: bool,
    index: u16,
    sub: u8,
    data: Vec<u8>,
    protocol: Protocol,
    /// Block transfers: bytes received in the current sub-block, in sequence.
    block_data: Vec<u8>,
    expected_seq: u8,
    /// Set when the data is complete; reported when the other side confirms.
    complete: bool,
}

impl Transfer {
    fn new(upload: bool, index: u16, sub: u8, protocol: Protocol) -> Transfer {
        Transfer {
            upload,
            index,
            sub,
            data: Vec::new(),
            protocol,
            block_data: Vec::new(),
            expected_seq: 1,
            complete: false,
        }
    }

    /// Inside a sub-block, before the last segment.
    fn in_subblock(&self) -> bool {
        self.protocol == Protocol::Block && !self.complete
    }

    /// Keep what the receiver acknowledged of the sub-block; the rest will be repeated.
    fn acknowledged(&mut self, ackseq: u8) {
        let keep = (usize::from(ackseq) * 7).min(self.block_data.len());
        let acked: Vec<u8> = self.block_data.drain(..).take(keep).collect();
        self.data.extend_from_slice(&acked);
        if usize::from(ackseq) < usize::from(self.expected_seq.saturating_sub(1)) {
            self.complete = false;
        }
        self.expected_seq = 1;
    }

    /// The end frame says how many bytes of the last segment are no data.
    fn ended(&mut self, unused: u8) {
        let keep = self.data.len().saturating_sub(usize::from(unused));
        self.data.truncate(keep);
        self.complete = true;
    }
}

/// Reassembles whole SDO transfers from the frames of the default channels, for bus monitors.
/// Feed every frame; complete and aborted transfers come out.
#[derive(Debug, Default)]
pub struct SdoTracker {
    transfers: HashMap<u8, Transfer>,
}

impl SdoTracker {
    /// A tracker with nothing in progress.
    pub fn new() -> Self {
        Self::default()
    }

    fn finish(
        &mut self,
        node: u8,
        result: Option<Result<Vec<u8>, AbortCode>>,
    ) -> Option<SdoTransfer> {
        let t = self.transfers.remove(&node)?;
        Some(SdoTransfer {
            node,
            upload: t.upload,
            index: t.index,
            sub: t.sub,
            result: result.unwrap_or(Ok(t.data)),
            protocol: t.protocol,
        })
    }

    /// Take one frame; returns a transfer that this frame finished.
    pub fn feed(&mut self, frame: &Frame) -> Option<SdoTransfer> {
        let CanId::Standard(id) = frame.id() else {
            return None;
        };
        let (request, node) = match classify(id) {
            Function::SdoRequest(n) => (true, n),
            Function::SdoResponse(n) => (false, n),
            _ => return None,
        };
        let d: &Payload = frame.data().try_into().ok()?;
        let in_subblock = self.transfers.get(&node).is_some_and(Transfer::in_subblock);
        if let Some(t) = self.transfers.get_mut(&node) {
            // Inside a sub-block, frames of the sending side are segments.
            let sending_side = t.upload != request;
            if in_subblock && sending_side && d[0] != 0x80 {
                let s = BlockSegment::read(d);
                if s.seq == t.expected_seq {
                    t.block_data.extend_from_slice(s.data);
                    t.expected_seq += 1;
                    t.complete |= s.last;
                }
                return None;
            }
        }
        if msg::is_abort(d, in_subblock) {
            let code = AbortCode(u32::from_le_bytes([d[4], d[5], d[6], d[7]]));
            return self.finish(node, Some(Err(code)));
        }
        if request {
            self.request(node, Request::read(d).ok()?)
        } else {
            self.response(node, Response::read(d).ok()?)
        }
    }

    fn request(&mut self, node: u8, r: Request<'_>) -> Option<SdoTransfer> {
        match r {
            Request::InitiateDownload { index, sub, data } => {
                let mut t = Transfer::new(false, index, sub, Protocol::Segmented);
                if let Initiate::Expedited { data, .. } = data {
                    t.protocol = Protocol::Expedited;
                    t.data = data.to_vec();
                    t.complete = true;
                }
                self.transfers.insert(node, t);
            }
            Request::InitiateUpload { index, sub } => {
                let t = Transfer::new(true, index, sub, Protocol::Segmented);
                self.transfers.insert(node, t);
            }
            Request::BlockUpload { index, sub, .. } => {
                let t = Transfer::new(true, index, sub, Protocol::Block);
                self.transfers.insert(node, t);
            }
            Request::BlockDownload { index, sub, .. } => {
                let t = Transfer::new(false, index, sub, Protocol::Block);
                self.transfers.insert(node, t);
            }
            Request::DownloadSegment { last, data, .. } => {
                let t = self.transfers.get_mut(&node)?;
                t.data.extend_from_slice(data);
                t.complete |= last;
            }
            Request::BlockUploadAck { ackseq, .. } => {
                self.transfers.get_mut(&node)?.acknowledged(ackseq)
            }
            Request::BlockDownloadEnd { unused, .. } => {
                self.transfers.get_mut(&node)?.ended(unused)
            }
            Request::BlockUploadEnd => return self.finish(node, None),
            Request::UploadSegment { .. } | Request::BlockUploadStart | Request::Abort { .. } => {}
        }
        None
    }

    fn response(&mut self, node: u8, r: Response<'_>) -> Option<SdoTransfer> {
        match r {
            Response::InitiateUpload { data, .. } => {
                let t = self.transfers.get_mut(&node)?;
                if let Initiate::Expedited { data, .. } = data {
                    t.protocol = Protocol::Expedited;
                    return self.finish(node, Some(Ok(data.to_vec())));
                }
                t.protocol = Protocol::Segmented;
            }
            Response::UploadSegment { last, data, .. } => {
                self.transfers.get_mut(&node)?.data.extend_from_slice(data);
                if last {
                    return self.finish(node, None);
                }
            }
            // The server confirms a download (initiate or segment) that is complete.
            Response::InitiateDownload { .. } | Response::DownloadSegment { .. }
                if self
                    .transfers
                    .get(&node)
                    .is_some_and(|t| t.complete && !t.upload) =>
            {
                return self.finish(node, None);
            }
            Response::BlockDownloadAck { ackseq, .. } => {
                self.transfers.get_mut(&node)?.acknowledged(ackseq)
            }
            Response::BlockUploadEnd { unused, .. } => self.transfers.get_mut(&node)?.ended(unused),
            Response::BlockDownloadEnd => return self.finish(node, None),
            _ => {}
        }
        None
    }
}

#[cfg(test)]
mod tests {
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
