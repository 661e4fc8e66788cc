//! SDO server, sans-IO (CiA 301 §7.2.4.3): one server channel's state machine.
//!
//! Feed it every request payload with [`SdoServer::handle`] and call
//! [`SdoServer::handle_timeout`] once [`SdoServer::poll_timeout`] has passed. Responses are pushed
//! into `out`; a block upload pushes a whole block at once.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use super::abort::AbortCode;
use super::crc::Crc16;
use super::msg::{self, BlockSegment, Initiate, Request, Response};
use super::{size_indication, Payload, SubBlockReceiver, MAX_BLOCK_SIZE, SEGMENT_DATA};
use crate::od::{ObjectDictionary, Reader, WriteGuard, Writer};
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

impl Segment {
    fn frame(&self, seq: u8, last: bool) -> Payload {
        let data = &self.data[..self.len];
        BlockSegment { seq, last, data }.write()
    }
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
        out.push(msg::abort(self.mux.0, self.mux.1, code));
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
        let in_subblock = matches!(self.state, State::BlockDownload(_));
        if msg::is_abort(req, in_subblock) {
            if let (true, Ok(Request::Abort { code, .. })) = (self.is_busy(), Request::read(req)) {
                tracing::debug!(%code, "SDO transfer aborted by client");
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
        if let State::BlockDownload(b) = state {
            // Inside a sub-block every frame is a data segment.
            return self.block_download_segment(b, BlockSegment::read(req), out);
        }
        if let State::Idle = state {
            // An abort answering a bad frame names the object the frame names.
            self.mux = (u16::from_le_bytes([req[1], req[2]]), req[3]);
        }
        match (state, Request::read(req)?) {
            (State::Idle, Request::InitiateDownload { data, .. }) => {
                self.initiate_download(od, data, out)
            }
            (State::Idle, Request::InitiateUpload { .. }) => self.initiate_upload(od, out),
            (State::Idle, Request::BlockDownload { crc, size, .. }) => {
                self.initiate_block_download(od, crc, size, out)
            }
            (
                State::Idle,
                Request::BlockUpload {
                    crc, blksize, pst, ..
                },
            ) => self.initiate_block_upload(od, crc, blksize, pst, out),
            (State::Download(d), Request::DownloadSegment { toggle, last, data }) => {
                self.download_segment(d, od, toggle, last, data, out)
            }
            (State::Upload(u), Request::UploadSegment { toggle }) => {
                self.upload_segment(u, toggle, out)
            }
            (State::BlockDownloadEnd(b), Request::BlockDownloadEnd { unused, crc }) => {
                Self::end_block_download(b, od, unused, crc, out)
            }
            (State::BlockUpload(b), request) => self.block_upload_step(b, request, out),
            _ => Err(AbortCode::COMMAND),
        }
    }

    fn initiate_download(
        &mut self,
        od: &mut ObjectDictionary,
        data: Initiate<'_>,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let (index, sub) = self.mux;
        let size = match data {
            Initiate::Expedited { mut data, sized } => {
                // Without a size indication the client sends 4 bytes; a shorter fixed-size
                // object takes its own length from them (CiA 301 leaves the rest unspecified).
                if let (false, Some(len)) = (sized, od.variable(index, sub)?.data_type.size()) {
                    data = &data[..len.min(4)];
                }
                od.write(index, sub, data)?;
                out.push(Response::InitiateDownload { index, sub }.write());
                return Ok(());
            }
            Initiate::Size(n) => Some(u64::from(n)),
            Initiate::Unsized => None,
        };
        let writer = od.open_write(index, sub, size)?;
        out.push(Response::InitiateDownload { index, sub }.write());
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
        toggle: bool,
        last: bool,
        data: &[u8],
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        if toggle != d.toggle {
            return Err(AbortCode::TOGGLE);
        }
        d.writer.write(data)?;
        if last {
            if d.size.is_some_and(|s| s != d.writer.written()) {
                return Err(AbortCode::LENGTH_MISMATCH);
            }
            d.writer.finish(od)?;
        } else {
            d.toggle = !d.toggle;
            self.state = State::Download(d);
        }
        out.push(Response::DownloadSegment { toggle }.write());
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
            let data = Initiate::Expedited {
                data: &data[..n],
                sized: true,
            };
            out.push(Response::InitiateUpload { index, sub, data }.write());
            return Ok(());
        }
        let data = match size_indication(size)? {
            Some(n) => Initiate::Size(n),
            None => Initiate::Unsized,
        };
        out.push(Response::InitiateUpload { index, sub, data }.write());
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
        toggle: bool,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        if toggle != u.toggle {
            return Err(AbortCode::TOGGLE);
        }
        let mut data = [0u8; SEGMENT_DATA];
        let n = fill(&mut u.reader, &mut data)?;
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
        out.push(
            Response::UploadSegment {
                toggle,
                last,
                data: &data[..n],
            }
            .write(),
        );
        if !last {
            u.toggle = !u.toggle;
            self.state = State::Upload(u);
        }
        Ok(())
    }

    fn initiate_block_download(
        &mut self,
        od: &mut ObjectDictionary,
        client_crc: bool,
        size: Option<u32>,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let (index, sub) = self.mux;
        let size = size.map(u64::from);
        let writer = od.open_write(index, sub, size)?;
        let blksize = self.config.block_size.clamp(1, MAX_BLOCK_SIZE);
        out.push(
            Response::BlockDownload {
                index,
                sub,
                crc: self.config.crc,
                blksize,
            }
            .write(),
        );
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
        segment: BlockSegment<'_>,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let received = b.receiver.segment(segment)?;
        if let Some(data) = received.data {
            b.writer.write(data)?;
            if let Some(crc) = &mut b.crc {
                crc.update(data);
            }
        }
        out.extend(received.ack.map(|a| {
            Response::BlockDownloadAck {
                ackseq: a.ackseq,
                blksize: a.blksize,
            }
            .write()
        }));
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
        unused: u8,
        crc: u16,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let tail = b.receiver.tail(unused);
        b.writer.write(&tail)?;
        if let Some(mut ours) = b.crc {
            ours.update(&tail);
            if ours.value() != crc {
                return Err(AbortCode::CRC);
            }
        }
        if b.size.is_some_and(|s| s != b.writer.written()) {
            return Err(AbortCode::LENGTH_MISMATCH);
        }
        b.writer.finish(od)?;
        out.push(Response::BlockDownloadEnd.write());
        Ok(())
    }

    fn initiate_block_upload(
        &mut self,
        od: &mut ObjectDictionary,
        client_crc: bool,
        blksize: u8,
        pst: u8,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let (index, sub) = self.mux;
        if !(1..=MAX_BLOCK_SIZE).contains(&blksize) {
            return Err(AbortCode::BLOCK_SIZE);
        }
        let reader = od.open_read(index, sub)?;
        let size = reader.size();
        if pst > 0 && size.is_some_and(|s| s <= u64::from(pst)) {
            // Protocol switch (CiA 301 §7.2.4.3.9): small values go by the normal upload.
            return self.initiate_upload(od, out);
        }
        out.push(
            Response::BlockUpload {
                index,
                sub,
                crc: self.config.crc,
                size: size_indication(size)?,
            }
            .write(),
        );
        self.state = State::BlockUpload(BlockUpload {
            reader,
            crc: (client_crc && self.config.crc).then(Crc16::new),
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
        request: Request<'_>,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        match (b.phase, request) {
            (UploadPhase::Start, Request::BlockUploadStart) => b.send_block(out)?,
            (UploadPhase::Ack, Request::BlockUploadAck { ackseq, blksize }) => {
                b.acknowledge(ackseq, blksize, out)?
            }
            (UploadPhase::End, Request::BlockUploadEnd) => return Ok(()),
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
            out.push(segment.frame(seq, last));
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
            out.push(segment.frame(seq, last));
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
            out.push(
                BlockSegment {
                    seq: 1,
                    last: true,
                    data: &[],
                }
                .write(),
            );
        }
        self.phase = UploadPhase::Ack;
        Ok(())
    }

    fn acknowledge(
        &mut self,
        ackseq: u8,
        blksize: u8,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let ackseq = usize::from(ackseq);
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
            let end = Response::BlockUploadEnd {
                unused: (SEGMENT_DATA - last_len.unwrap_or(0)) as u8,
                crc: self.crc.map(Crc16::value).unwrap_or(0),
            };
            out.push(end.write());
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
        let cob = |sub| {
            od.get_u32(index, sub)
                .and_then(crate::cob::id_from_parameter)
        };
        if let (Some(rx), Some(tx)) = (cob(1), cob(2)) {
            channels.push((rx, tx));
        }
    }
    channels
}

/// Enforces on network writes the rule of CiA 301 §7.5.2.33 for the further SDO server
/// channels (1201h–127Fh, subs 1 and 2): a channel's identifiers change only while it is not
/// valid ([`crate::cob::check_parameter_write`]), and a valid one is not one of the node's
/// identifiers in use — another channel's or a valid PDO's (CiA 301 §7.3.5: one identifier,
/// one producer; a channel moved onto a PDO would answer its requests in the PDO's frames).
/// 1200h, the default channel, is read-only.
pub struct SdoServerGuard;

impl WriteGuard for SdoServerGuard {
    fn check(
        &self,
        od: &ObjectDictionary,
        index: u16,
        sub: u8,
        data: &[u8],
    ) -> Result<(), AbortCode> {
        if !(0x1201..=0x127F).contains(&index) || !(1..=2).contains(&sub) {
            return Ok(());
        }
        let new = u32::from_le_bytes(data.try_into().map_err(|_| AbortCode::LENGTH_MISMATCH)?);
        let old = od.get_u32(index, sub).unwrap_or(crate::cob::COB_INVALID);
        crate::cob::check_parameter_write(old, new, |id| {
            crate::cob::used_by_sdo_channel(od, (index, sub), id)
                || crate::cob::used_by_tpdo(od, (index, sub), id)
                || crate::cob::used_by_rpdo(od, (index, sub), id)
        })
    }
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

    /// Serve `channels` from now on: a channel that stays keeps its transfer in progress, one
    /// that goes ends its transfer without a word (its identifiers are no longer valid), a new one
    /// starts idle.
    pub fn reconfigure(&mut self, channels: Vec<(CanId, CanId)>, config: &ServerConfig) {
        let mut before = std::mem::take(&mut self.channels);
        self.channels = channels
            .into_iter()
            .map(|(rx, tx)| {
                let kept = before
                    .iter()
                    .position(|&(r, t, _)| (r, t) == (rx, tx))
                    .map(|i| before.swap_remove(i).2);
                (
                    rx,
                    tx,
                    kept.unwrap_or_else(|| SdoServer::new(config.clone())),
                )
            })
            .collect();
    }

    /// Acceptance filters for the request COB-IDs.
    pub fn filters(&self) -> Vec<Filter> {
        self.channels
            .iter()
            .map(|&(rx, _, _)| Filter::exact(rx))
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
