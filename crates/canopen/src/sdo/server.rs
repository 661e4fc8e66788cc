//! SDO server, sans-IO (CiA 301 §7.2.4.3): one server channel's state machine.
//!
//! Feed it every request payload with [`SdoServer::handle`] and call
//! [`SdoServer::handle_timeout`] once [`SdoServer::poll_timeout`] has passed. Responses are pushed
//! into `out`; a block upload pushes a whole block at once.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use super::abort::AbortCode;
use super::crc::Crc16;
use super::{
    abort_code, abort_payload, block_segment, mux, size_indication, with_mux, Payload,
    SubBlockReceiver, MAX_BLOCK_SIZE, SEGMENT_DATA,
};
use crate::od::{ObjectDictionary, Reader, Writer};
use crate::types::Value;
use canbus::{CanId, Filter, Frame};

/// How a server channel behaves.
#[derive(Debug, Clone)]
pub struct ServerConfig {
    /// How long the server waits for the client's next frame inside a transfer.
    pub timeout: Duration,
    /// Segments per block the server asks for in block downloads (1–127).
    pub block_size: u8,
    /// Whether the server offers CRC in block transfers.
    pub crc: bool,
}

impl Default for ServerConfig {
    fn default() -> Self {
        ServerConfig {
            timeout: super::DEFAULT_TIMEOUT,
            block_size: MAX_BLOCK_SIZE,
            crc: true,
        }
    }
}

/// One segment of block-upload data: bytes and how many are valid.
#[derive(Clone, Copy)]
struct Segment {
    data: [u8; SEGMENT_DATA],
    len: usize,
}

struct Download {
    writer: Writer,
    toggle: bool,
    size: Option<u64>,
}

struct Upload {
    reader: Reader,
    toggle: bool,
    size: Option<u64>,
    sent: u64,
}

struct BlockDownload {
    writer: Writer,
    size: Option<u64>,
    crc: Option<Crc16>,
    receiver: SubBlockReceiver,
}

#[derive(Clone, Copy, PartialEq, Eq)]
/// What a block upload waits for from the client.
enum UploadPhase {
    Start,
    Ack,
    End,
}

struct BlockUpload {
    reader: Reader,
    crc: Option<Crc16>,
    blksize: u8,
    /// Sent and not yet acknowledged, oldest first.
    unacked: VecDeque<Segment>,
    /// Read ahead, to know whether the segment before it was the last.
    lookahead: Option<Segment>,
    /// The reader has nothing more (beyond `lookahead`).
    exhausted: bool,
    phase: UploadPhase,
}

enum State {
    Idle,
    Download(Download),
    Upload(Upload),
    /// Receiving the segments of a sub-block.
    BlockDownload(BlockDownload),
    /// The last segment arrived; waiting for the end frame.
    BlockDownloadEnd(BlockDownload),
    BlockUpload(BlockUpload),
}

/// One SDO server channel.
pub struct SdoServer {
    config: ServerConfig,
    state: State,
    /// Index and sub-index of the transfer in progress (for aborts).
    mux: (u16, u8),
    deadline: Option<Instant>,
}

/// Read into `buf` until it is full or the reader ends.
fn fill(reader: &mut Reader, buf: &mut [u8]) -> Result<usize, AbortCode> {
    let mut filled = 0;
    while filled < buf.len() {
        let n = reader.read(&mut buf[filled..])?;
        if n == 0 {
            break;
        }
        filled += n;
    }
    Ok(filled)
}

fn read_segment(reader: &mut Reader) -> Result<Option<Segment>, AbortCode> {
    let mut data = [0u8; SEGMENT_DATA];
    let len = fill(reader, &mut data)?;
    Ok((len > 0).then_some(Segment { data, len }))
}

fn size_field(req: &Payload) -> u64 {
    u64::from(u32::from_le_bytes([req[4], req[5], req[6], req[7]]))
}

impl SdoServer {
    /// An idle server channel.
    pub fn new(config: ServerConfig) -> Self {
        SdoServer {
            config,
            state: State::Idle,
            mux: (0, 0),
            deadline: None,
        }
    }

    /// Whether a transfer is in progress.
    pub fn is_busy(&self) -> bool {
        !matches!(self.state, State::Idle)
    }

    /// When [`Self::handle_timeout`] must be called, if a transfer is in progress.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.deadline
    }

    /// Abort a transfer whose client went silent (abort code 0x05040000).
    pub fn handle_timeout(&mut self, now: Instant, out: &mut Vec<Payload>) {
        if self.deadline.is_some_and(|d| now >= d) {
            tracing::debug!(
                index = self.mux.0,
                sub = self.mux.1,
                "SDO server transfer timed out"
            );
            self.fail(AbortCode::TIMEOUT, out);
        }
    }

    fn fail(&mut self, code: AbortCode, out: &mut Vec<Payload>) {
        out.push(abort_payload(self.mux.0, self.mux.1, code));
        self.state = State::Idle;
        self.deadline = None;
    }

    /// Handle one request payload from the client.
    pub fn handle(
        &mut self,
        od: &mut ObjectDictionary,
        req: &Payload,
        now: Instant,
        out: &mut Vec<Payload>,
    ) {
        // Inside a sub-block every frame is a data segment; 0x80 (last segment, sequence 0)
        // cannot be one, so it is the client's abort.
        let in_subblock = matches!(self.state, State::BlockDownload(_));
        if req[0] == 0x80 || (!in_subblock && req[0] >> 5 == 4) {
            if self.is_busy() {
                tracing::debug!(code = %abort_code(req), "SDO transfer aborted by client");
            }
            self.state = State::Idle;
            self.deadline = None;
            return;
        }
        let state = std::mem::replace(&mut self.state, State::Idle);
        if let Err(code) = self.step(state, od, req, out) {
            self.fail(code, out);
        }
        self.deadline = self.is_busy().then(|| now + self.config.timeout);
    }

    fn step(
        &mut self,
        state: State,
        od: &mut ObjectDictionary,
        req: &Payload,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let ccs = req[0] >> 5;
        match state {
            State::Idle => {
                self.mux = mux(req);
                match ccs {
                    1 => self.initiate_download(od, req, out),
                    2 => self.initiate_upload(od, out),
                    6 if req[0] & 1 == 0 => self.initiate_block_download(od, req, out),
                    5 if req[0] & 3 == 0 => self.initiate_block_upload(od, req, out),
                    _ => Err(AbortCode::COMMAND),
                }
            }
            State::Download(d) if ccs == 0 => self.download_segment(d, od, req, out),
            State::Upload(u) if ccs == 3 => self.upload_segment(u, req, out),
            State::BlockDownload(b) => self.block_download_segment(b, req, out),
            State::BlockDownloadEnd(b) if ccs == 6 && req[0] & 1 == 1 => {
                Self::end_block_download(b, od, req, out)
            }
            State::BlockUpload(b) if ccs == 5 => self.block_upload_step(b, req, out),
            _ => Err(AbortCode::COMMAND),
        }
    }

    fn initiate_download(
        &mut self,
        od: &mut ObjectDictionary,
        req: &Payload,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let (index, sub) = self.mux;
        let expedited = req[0] & 2 != 0;
        let sized = req[0] & 1 != 0;
        if expedited {
            let n = if sized {
                usize::from((req[0] >> 2) & 3)
            } else {
                0
            };
            let mut data = &req[4..8 - n];
            // Without a size indication the client sends 4 bytes; a shorter fixed-size object
            // takes its own length from them (CiA 301 leaves the rest unspecified).
            if let (false, Some(len)) = (sized, od.variable(index, sub)?.data_type.size()) {
                data = &data[..len.min(4)];
            }
            od.write(index, sub, data)?;
            out.push(with_mux(0x60, index, sub, [0; 4]));
            return Ok(());
        }
        let size = sized.then(|| size_field(req));
        let writer = od.open_write(index, sub, size)?;
        out.push(with_mux(0x60, index, sub, [0; 4]));
        self.state = State::Download(Download {
            writer,
            toggle: false,
            size,
        });
        Ok(())
    }

    fn download_segment(
        &mut self,
        mut d: Download,
        od: &mut ObjectDictionary,
        req: &Payload,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        if (req[0] & 0x10 != 0) != d.toggle {
            return Err(AbortCode::TOGGLE);
        }
        let n = usize::from((req[0] >> 1) & 7);
        d.writer.write(&req[1..8 - n])?;
        let response = [0x20 | (req[0] & 0x10), 0, 0, 0, 0, 0, 0, 0];
        if req[0] & 1 == 1 {
            if d.size.is_some_and(|s| s != d.writer.written()) {
                return Err(AbortCode::LENGTH_MISMATCH);
            }
            d.writer.finish(od)?;
        } else {
            d.toggle = !d.toggle;
            self.state = State::Download(d);
        }
        out.push(response);
        Ok(())
    }

    fn initiate_upload(
        &mut self,
        od: &mut ObjectDictionary,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let (index, sub) = self.mux;
        let mut reader = od.open_read(index, sub)?;
        let size = reader.size();
        // Expedited carries 1-4 bytes (n has two bits); an empty value goes segmented.
        if let Some(size @ 1..=4) = size {
            let mut data = [0u8; 4];
            let n = fill(&mut reader, &mut data[..size as usize])?;
            out.push(with_mux(0x43 | ((4 - n) as u8) << 2, index, sub, data));
            return Ok(());
        }
        let (sized, field) = size_indication(size)?;
        out.push(with_mux(0x40 | u8::from(sized), index, sub, field));
        self.state = State::Upload(Upload {
            reader,
            toggle: false,
            size,
            sent: 0,
        });
        Ok(())
    }

    fn upload_segment(
        &mut self,
        mut u: Upload,
        req: &Payload,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        if (req[0] & 0x10 != 0) != u.toggle {
            return Err(AbortCode::TOGGLE);
        }
        let mut p = [0u8; 8];
        let n = fill(&mut u.reader, &mut p[1..8])?;
        u.sent += n as u64;
        // With a known size the last segment is the one that reaches it; a stream of unknown
        // size ends with a short segment (an empty one if it ends on a segment boundary).
        let last = match u.size {
            Some(size) => u.sent >= size,
            None => n < SEGMENT_DATA,
        };
        if u.size
            .is_some_and(|s| u.sent > s || (n < SEGMENT_DATA && u.sent < s))
        {
            // The value changed size under the transfer.
            return Err(AbortCode::GENERAL);
        }
        p[0] = (req[0] & 0x10) | ((SEGMENT_DATA - n) as u8) << 1 | u8::from(last);
        out.push(p);
        if !last {
            u.toggle = !u.toggle;
            self.state = State::Upload(u);
        }
        Ok(())
    }

    fn initiate_block_download(
        &mut self,
        od: &mut ObjectDictionary,
        req: &Payload,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let (index, sub) = self.mux;
        let client_crc = req[0] & 4 != 0;
        let size = (req[0] & 2 != 0).then(|| size_field(req));
        let writer = od.open_write(index, sub, size)?;
        let blksize = self.config.block_size.clamp(1, MAX_BLOCK_SIZE);
        let sc = if self.config.crc { 4 } else { 0 };
        out.push(with_mux(0xA0 | sc, index, sub, [blksize, 0, 0, 0]));
        self.state = State::BlockDownload(BlockDownload {
            writer,
            size,
            crc: (client_crc && self.config.crc).then(Crc16::new),
            receiver: SubBlockReceiver::new(blksize),
        });
        Ok(())
    }

    fn block_download_segment(
        &mut self,
        mut b: BlockDownload,
        req: &Payload,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let received = b.receiver.segment(req)?;
        if let Some(data) = received.data {
            b.writer.write(data)?;
            if let Some(crc) = &mut b.crc {
                crc.update(data);
            }
        }
        out.extend(received.ack);
        self.state = if received.complete {
            State::BlockDownloadEnd(b)
        } else {
            State::BlockDownload(b)
        };
        Ok(())
    }

    fn end_block_download(
        mut b: BlockDownload,
        od: &mut ObjectDictionary,
        req: &Payload,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let tail = b.receiver.tail(req[0]);
        b.writer.write(&tail)?;
        if let Some(mut crc) = b.crc {
            crc.update(&tail);
            if crc.value() != u16::from_le_bytes([req[1], req[2]]) {
                return Err(AbortCode::CRC);
            }
        }
        if b.size.is_some_and(|s| s != b.writer.written()) {
            return Err(AbortCode::LENGTH_MISMATCH);
        }
        b.writer.finish(od)?;
        out.push([0xA1, 0, 0, 0, 0, 0, 0, 0]);
        Ok(())
    }

    fn initiate_block_upload(
        &mut self,
        od: &mut ObjectDictionary,
        req: &Payload,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let (index, sub) = self.mux;
        let (blksize, pst) = (req[4], req[5]);
        if !(1..=MAX_BLOCK_SIZE).contains(&blksize) {
            return Err(AbortCode::BLOCK_SIZE);
        }
        let reader = od.open_read(index, sub)?;
        let size = reader.size();
        if pst > 0 && size.is_some_and(|s| s <= u64::from(pst)) {
            // Protocol switch (CiA 301 §7.2.4.3.9): small values go by the normal upload.
            return self.initiate_upload(od, out);
        }
        let sc = if self.config.crc { 4 } else { 0 };
        let (sized, field) = size_indication(size)?;
        out.push(with_mux(
            0xC0 | sc | u8::from(sized) << 1,
            index,
            sub,
            field,
        ));
        self.state = State::BlockUpload(BlockUpload {
            reader,
            crc: (req[0] & 4 != 0 && self.config.crc).then(Crc16::new),
            blksize,
            unacked: VecDeque::new(),
            lookahead: None,
            exhausted: false,
            phase: UploadPhase::Start,
        });
        Ok(())
    }

    fn block_upload_step(
        &mut self,
        mut b: BlockUpload,
        req: &Payload,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        match (b.phase, req[0] & 3) {
            (UploadPhase::Start, 3) => b.send_block(out)?,
            (UploadPhase::Ack, 2) => b.acknowledge(req, out)?,
            (UploadPhase::End, 1) => return Ok(()),
            _ => return Err(AbortCode::COMMAND),
        }
        self.state = State::BlockUpload(b);
        Ok(())
    }
}

impl BlockUpload {
    fn done_reading(&self) -> bool {
        self.exhausted && self.lookahead.is_none()
    }

    /// The next new segment and whether it is the last one (reading one segment ahead).
    fn next_segment(&mut self) -> Result<Option<(Segment, bool)>, AbortCode> {
        let current = match self.lookahead.take() {
            Some(s) => s,
            None if self.exhausted => return Ok(None),
            None => match read_segment(&mut self.reader)? {
                Some(s) => s,
                None => {
                    self.exhausted = true;
                    return Ok(None);
                }
            },
        };
        if current.len < SEGMENT_DATA {
            self.exhausted = true;
            return Ok(Some((current, true)));
        }
        if !self.exhausted {
            self.lookahead = read_segment(&mut self.reader)?;
            self.exhausted = self.lookahead.is_none();
        }
        Ok(Some((current, self.lookahead.is_none())))
    }

    /// Send a sub-block: first the segments the client did not acknowledge, then new data.
    fn send_block(&mut self, out: &mut Vec<Payload>) -> Result<(), AbortCode> {
        let mut seq = 0u8;
        let resend = self.unacked.len().min(usize::from(self.blksize));
        for (i, segment) in self.unacked.iter().take(resend).enumerate() {
            seq += 1;
            let last = self.done_reading() && i + 1 == self.unacked.len();
            out.push(block_segment(seq, last, &segment.data[..segment.len]));
        }
        // New data follows only once everything unacknowledged has been resent.
        let add_new = resend == self.unacked.len() && !(self.done_reading() && resend > 0);
        while add_new && seq < self.blksize {
            let Some((segment, last)) = self.next_segment()? else {
                break;
            };
            if let Some(crc) = &mut self.crc {
                crc.update(&segment.data[..segment.len]);
            }
            seq += 1;
            out.push(block_segment(seq, last, &segment.data[..segment.len]));
            self.unacked.push_back(segment);
            if last {
                break;
            }
        }
        if seq == 0 {
            // An empty value: one last segment without data.
            self.unacked.push_back(Segment {
                data: [0; SEGMENT_DATA],
                len: 0,
            });
            out.push(block_segment(1, true, &[]));
        }
        self.phase = UploadPhase::Ack;
        Ok(())
    }

    fn acknowledge(&mut self, req: &Payload, out: &mut Vec<Payload>) -> Result<(), AbortCode> {
        let ackseq = usize::from(req[1]);
        let blksize = req[2];
        let sent_in_block = self.unacked.len().min(usize::from(self.blksize));
        if ackseq > sent_in_block {
            return Err(AbortCode::SEQUENCE);
        }
        if !(1..=MAX_BLOCK_SIZE).contains(&blksize) {
            return Err(AbortCode::BLOCK_SIZE);
        }
        let last_len = ackseq
            .checked_sub(1)
            .and_then(|i| self.unacked.get(i))
            .map(|s| s.len);
        self.unacked.drain(..ackseq);
        self.blksize = blksize;
        if self.unacked.is_empty() && self.done_reading() {
            let n = (SEGMENT_DATA - last_len.unwrap_or(0)) as u8;
            let crc = self.crc.map(Crc16::value).unwrap_or(0).to_le_bytes();
            out.push([0xC1 | n << 2, crc[0], crc[1], 0, 0, 0, 0, 0]);
            self.phase = UploadPhase::End;
            return Ok(());
        }
        self.send_block(out)
    }
}

/// The default SDO channel of a node: requests on 0x600 + node-ID, responses on 0x580 + node-ID.
pub fn default_channel(node_id: u8) -> (CanId, CanId) {
    (
        CanId::Standard(0x600 + u16::from(node_id & 0x7F)),
        CanId::Standard(0x580 + u16::from(node_id & 0x7F)),
    )
}

/// The server channels of a node: the default channel (0x1200, always present per CiA 301) and
/// (request COB-ID, response COB-ID) of every further valid SDO server parameter object
/// 0x1201–0x127F.
pub fn server_channels(od: &ObjectDictionary, node_id: u8) -> Vec<(CanId, CanId)> {
    let mut channels = vec![default_channel(node_id)];
    for index in 0x1201..=0x127F {
        let cob = |sub| match od.get_value(index, sub) {
            Ok(Value::Uint(v)) => u32::try_from(v)
                .ok()
                .and_then(crate::cob::id_from_parameter),
            _ => None,
        };
        if let (Some(rx), Some(tx)) = (cob(1), cob(2)) {
            channels.push((rx, tx));
        }
    }
    channels
}

/// Every SDO server channel of a node, with requests dispatched by COB-ID.
pub struct ServerChannels {
    channels: Vec<(CanId, CanId, SdoServer)>,
    payloads: Vec<Payload>,
}

impl ServerChannels {
    /// Servers for `channels` (request COB-ID, response COB-ID).
    pub fn new(channels: Vec<(CanId, CanId)>, config: &ServerConfig) -> Self {
        ServerChannels {
            channels: channels
                .into_iter()
                .map(|(rx, tx)| (rx, tx, SdoServer::new(config.clone())))
                .collect(),
            payloads: Vec::new(),
        }
    }

    /// Acceptance filters for the request COB-IDs.
    pub fn filters(&self) -> Vec<Filter> {
        self.channels
            .iter()
            .map(|(rx, _, _)| match rx {
                CanId::Standard(id) => Filter::standard(*id, 0x7FF),
                CanId::Extended(id) => Filter::extended(*id, 0x1FFF_FFFF),
            })
            .collect()
    }

    /// Whether `id` is the request identifier of one of the channels.
    pub fn serves(&self, id: CanId) -> bool {
        self.channels.iter().any(|(rx, _, _)| *rx == id)
    }

    /// Handle `frame` if it is a request on one of the channels; responses go to `out`.
    /// Returns whether the frame was an SDO request for this node.
    pub fn handle(
        &mut self,
        od: &mut ObjectDictionary,
        frame: &Frame,
        now: Instant,
        out: &mut Vec<Frame>,
    ) -> bool {
        let Some((_, tx, server)) = self
            .channels
            .iter_mut()
            .find(|(rx, _, _)| *rx == frame.id())
        else {
            return false;
        };
        let Some(p) = super::payload(frame.data()) else {
            tracing::debug!(frame = %frame, "SDO request without 8 bytes ignored");
            return true;
        };
        self.payloads.clear();
        server.handle(od, &p, now, &mut self.payloads);
        out.extend(self.payloads.iter().filter_map(|p| Frame::new(*tx, p).ok()));
        true
    }

    /// The earliest transfer timeout of any channel.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.channels
            .iter()
            .filter_map(|(_, _, s)| s.poll_timeout())
            .min()
    }

    /// Abort transfers whose client went silent.
    pub fn handle_timeout(&mut self, now: Instant, out: &mut Vec<Frame>) {
        for (_, tx, server) in &mut self.channels {
            self.payloads.clear();
            server.handle_timeout(now, &mut self.payloads);
            out.extend(self.payloads.iter().filter_map(|p| Frame::new(*tx, p).ok()));
        }
    }
}
