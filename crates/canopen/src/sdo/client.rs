//! SDO client, sans-IO (CiA 301 §7.2.4.3): one transfer at a time on one client channel.
//!
//! Start a transfer with [`SdoClient::start_upload`] or [`SdoClient::start_download`], feed
//! every response payload to [`SdoClient::handle`] and call [`SdoClient::handle_timeout`] once
//! [`SdoClient::poll_timeout`] has passed; both return the outcome when the transfer ends.

use std::time::{Duration, Instant};

use super::abort::AbortCode;
use super::crc::Crc16;
use super::msg::{self, BlockSegment, Initiate, Request, Response};
use super::{Payload, SubBlockReceiver, MAX_BLOCK_SIZE, SEGMENT_DATA};

/// How a transfer fails.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum SdoError {
    /// The server aborted with this code.
    #[error("server aborted: {0}")]
    Aborted(AbortCode),
    /// The client aborted (and told the server) because the server broke the protocol.
    #[error("aborted by client: {0}")]
    Protocol(AbortCode),
    /// The server did not answer in time.
    #[error("SDO timeout: no response")]
    Timeout,
    /// A transfer is already in progress on this client.
    #[error("SDO client busy")]
    Busy,
}

impl SdoError {
    /// The abort code that describes the failure (timeouts: 0x05040000).
    pub fn abort_code(&self) -> AbortCode {
        match self {
            SdoError::Aborted(c) | SdoError::Protocol(c) => *c,
            SdoError::Timeout => AbortCode::TIMEOUT,
            SdoError::Busy => AbortCode::NO_RESOURCE,
        }
    }
}

/// How a client channel behaves.
#[derive(Debug, Clone)]
pub struct ClientConfig {
    /// How long to wait for each response.
    pub timeout: Duration,
    /// Segments per block the client asks for in block uploads (1–127).
    pub block_size: u8,
    /// Offer CRC in block transfers.
    pub crc: bool,
    /// Protocol switch threshold for block uploads: values up to this many bytes are sent by
    /// the server with the normal upload protocol (0: never switch).
    pub switch_threshold: u8,
}

impl Default for ClientConfig {
    fn default() -> Self {
        ClientConfig {
            timeout: super::DEFAULT_TIMEOUT,
            block_size: MAX_BLOCK_SIZE,
            crc: true,
            switch_threshold: 21,
        }
    }
}

/// How a transfer moves its data.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Transfer {
    /// Expedited when it fits in 4 bytes, segmented otherwise.
    Normal,
    /// Segmented even for 4 bytes or less.
    Segmented,
    /// Block transfer.
    Block,
}

/// What a finished transfer gives: the uploaded bytes not yet taken with
/// [`SdoClient::take_received`] (empty for a download), or the failure.
pub type Outcome = Result<Vec<u8>, SdoError>;

/// Where a download's data comes from. The client reads it segment by segment as the transfer
/// advances (and again for segments a block transfer must repeat), so a large DOMAIN never has
/// to be in memory at once.
pub trait DownloadSource: Send {
    /// Total bytes (sent as the size indication; at most 4 GiB − 1).
    fn len(&self) -> u64;
    /// Whether there are no bytes at all.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Fill `buf` with the bytes at `offset`.
    fn read_at(&mut self, offset: u64, buf: &mut [u8]) -> std::io::Result<()>;
}

impl DownloadSource for Vec<u8> {
    fn len(&self) -> u64 {
        self.as_slice().len() as u64
    }
    fn read_at(&mut self, offset: u64, buf: &mut [u8]) -> std::io::Result<()> {
        let start = usize::try_from(offset).map_err(std::io::Error::other)?;
        let slice = self
            .get(start..start + buf.len())
            .ok_or_else(|| std::io::Error::from(std::io::ErrorKind::UnexpectedEof))?;
        buf.copy_from_slice(slice);
        Ok(())
    }
}

/// A file as a download source.
pub struct FileSource {
    file: std::fs::File,
    len: u64,
}

impl FileSource {
    /// Open `path` for a download.
    pub fn open(path: &std::path::Path) -> std::io::Result<Self> {
        let file = std::fs::File::open(path)?;
        let len = file.metadata()?.len();
        Ok(FileSource { file, len })
    }
}

impl DownloadSource for FileSource {
    fn len(&self) -> u64 {
        self.len
    }
    fn read_at(&mut self, offset: u64, buf: &mut [u8]) -> std::io::Result<()> {
        use std::io::{Read, Seek, SeekFrom};
        self.file.seek(SeekFrom::Start(offset))?;
        self.file.read_exact(buf)
    }
}

enum State {
    Idle,
    DownloadInit {
        expedited: bool,
    },
    DownloadSegment {
        pos: u64,
        toggle: bool,
        last: bool,
    },
    UploadInit,
    UploadSegment {
        toggle: bool,
        size: Option<u64>,
    },
    BlockDownloadInit,
    BlockDownloadSub {
        block_start: u64,
        sent: u64,
        crc: bool,
    },
    BlockDownloadEnd,
    BlockUploadInit,
    BlockUploadSub(BlockUpload),
    BlockUploadEnd(BlockUpload),
}

struct BlockUpload {
    size: Option<u64>,
    crc: bool,
    receiver: SubBlockReceiver,
}

/// One SDO client channel.
pub struct SdoClient {
    config: ClientConfig,
    state: State,
    mux: (u16, u8),
    deadline: Option<Instant>,
    done: u64,
    total: Option<u64>,
    /// Download data.
    source: Option<Box<dyn DownloadSource>>,
    /// Uploaded bytes not yet taken.
    received: Vec<u8>,
    /// CRC over everything sent (block download) or received (block upload) so far.
    crc: Crc16,
    /// How far `crc` covers the download (segments repeated after a loss are not counted twice).
    crc_pos: u64,
}

impl SdoClient {
    /// An idle client.
    pub fn new(config: ClientConfig) -> Self {
        SdoClient {
            config,
            state: State::Idle,
            mux: (0, 0),
            deadline: None,
            done: 0,
            total: None,
            source: None,
            received: Vec::new(),
            crc: Crc16::new(),
            crc_pos: 0,
        }
    }

    /// Take the uploaded bytes received so far (for streaming a large upload elsewhere).
    pub fn take_received(&mut self) -> Vec<u8> {
        std::mem::take(&mut self.received)
    }

    /// Whether a transfer is in progress.
    pub fn is_busy(&self) -> bool {
        !matches!(self.state, State::Idle)
    }

    /// Bytes transferred so far and the total if known.
    pub fn progress(&self) -> (u64, Option<u64>) {
        (self.done, self.total)
    }

    /// When [`Self::handle_timeout`] must be called.
    pub fn poll_timeout(&self) -> Option<Instant> {
        self.deadline
    }

    fn begin(&mut self, index: u16, sub: u8, now: Instant) -> Result<(), SdoError> {
        if self.is_busy() {
            return Err(SdoError::Busy);
        }
        self.mux = (index, sub);
        self.deadline = Some(now + self.config.timeout);
        self.done = 0;
        self.total = None;
        self.source = None;
        self.received.clear();
        self.crc = Crc16::new();
        self.crc_pos = 0;
        Ok(())
    }

    /// Read `index`/`sub` from the server.
    pub fn start_upload(
        &mut self,
        index: u16,
        sub: u8,
        how: Transfer,
        now: Instant,
        out: &mut Vec<Payload>,
    ) -> Result<(), SdoError> {
        self.begin(index, sub, now)?;
        if how == Transfer::Block {
            let request = Request::BlockUpload {
                index,
                sub,
                crc: self.config.crc,
                blksize: self.config.block_size.clamp(1, MAX_BLOCK_SIZE),
                pst: self.config.switch_threshold,
            };
            out.push(request.write());
            self.state = State::BlockUploadInit;
        } else {
            out.push(Request::InitiateUpload { index, sub }.write());
            self.state = State::UploadInit;
        }
        Ok(())
    }

    /// Write `data` to `index`/`sub` on the server.
    pub fn start_download(
        &mut self,
        index: u16,
        sub: u8,
        data: Vec<u8>,
        how: Transfer,
        now: Instant,
        out: &mut Vec<Payload>,
    ) -> Result<(), SdoError> {
        self.start_download_from(index, sub, Box::new(data), how, now, out)
    }

    /// Write the bytes of `source` to `index`/`sub`, reading them as the transfer advances.
    pub fn start_download_from(
        &mut self,
        index: u16,
        sub: u8,
        mut source: Box<dyn DownloadSource>,
        how: Transfer,
        now: Instant,
        out: &mut Vec<Payload>,
    ) -> Result<(), SdoError> {
        let len = u32::try_from(source.len())
            .map_err(|_| SdoError::Protocol(AbortCode::LENGTH_TOO_HIGH))?;
        let expedited = how == Transfer::Normal && (1..=4).contains(&len);
        let mut d = [0u8; 4];
        if expedited {
            source
                .read_at(0, &mut d[..len as usize])
                .map_err(|_| SdoError::Protocol(AbortCode::GENERAL))?;
        }
        self.begin(index, sub, now)?;
        self.total = Some(len.into());
        let request = match how {
            _ if expedited => {
                self.state = State::DownloadInit { expedited: true };
                let data = Initiate::Expedited {
                    data: &d[..len as usize],
                    sized: true,
                };
                Request::InitiateDownload { index, sub, data }
            }
            Transfer::Block => {
                self.state = State::BlockDownloadInit;
                Request::BlockDownload {
                    index,
                    sub,
                    crc: self.config.crc,
                    size: Some(len),
                }
            }
            _ => {
                self.state = State::DownloadInit { expedited: false };
                let data = Initiate::Size(len);
                Request::InitiateDownload { index, sub, data }
            }
        };
        out.push(request.write());
        self.source = Some(source);
        Ok(())
    }

    /// Abort the transfer from this side with `code`.
    pub fn abort(&mut self, code: AbortCode, out: &mut Vec<Payload>) {
        if self.is_busy() {
            out.push(msg::abort(self.mux.0, self.mux.1, code));
        }
        self.state = State::Idle;
        self.deadline = None;
    }

    /// Give up on a silent server: abort it with 0x05040000 and report the timeout.
    pub fn handle_timeout(&mut self, now: Instant, out: &mut Vec<Payload>) -> Option<Outcome> {
        if self.deadline.is_none_or(|d| now < d) {
            return None;
        }
        self.abort(AbortCode::TIMEOUT, out);
        Some(Err(SdoError::Timeout))
    }

    /// Handle one response payload; returns the outcome when the transfer ends.
    pub fn handle(
        &mut self,
        resp: &Payload,
        now: Instant,
        out: &mut Vec<Payload>,
    ) -> Option<Outcome> {
        if !self.is_busy() {
            return None;
        }
        let in_subblock = matches!(self.state, State::BlockUploadSub(_));
        if msg::is_abort(resp, in_subblock) {
            self.state = State::Idle;
            self.deadline = None;
            let code = match Response::read(resp) {
                Ok(Response::Abort { code, .. }) => code,
                _ => AbortCode::GENERAL,
            };
            return Some(Err(SdoError::Aborted(code)));
        }
        self.deadline = Some(now + self.config.timeout);
        let state = std::mem::replace(&mut self.state, State::Idle);
        match self.step(state, resp, out) {
            Ok(None) => None,
            Ok(Some(data)) => {
                self.deadline = None;
                Some(Ok(data))
            }
            Err(code) => {
                self.abort_with(code, out);
                Some(Err(SdoError::Protocol(code)))
            }
        }
    }

    fn abort_with(&mut self, code: AbortCode, out: &mut Vec<Payload>) {
        out.push(msg::abort(self.mux.0, self.mux.1, code));
        self.state = State::Idle;
        self.deadline = None;
    }

    fn check_mux(&self, index: u16, sub: u8) -> Result<(), AbortCode> {
        if (index, sub) == self.mux {
            Ok(())
        } else {
            Err(AbortCode::GENERAL)
        }
    }

    fn step(
        &mut self,
        state: State,
        resp: &Payload,
        out: &mut Vec<Payload>,
    ) -> Result<Option<Vec<u8>>, AbortCode> {
        if let State::BlockUploadSub(b) = state {
            // Inside a sub-block every frame is a data segment.
            return self.block_upload_segment(b, BlockSegment::read(resp), out);
        }
        let len = self.total.unwrap_or(0);
        match (state, Response::read(resp)?) {
            (State::DownloadInit { expedited }, Response::InitiateDownload { index, sub }) => {
                self.check_mux(index, sub)?;
                if expedited {
                    self.done = len;
                    return Ok(Some(Vec::new()));
                }
                self.send_download_segment(0, false, out)?;
                Ok(None)
            }
            (
                State::DownloadSegment { pos, toggle, last },
                Response::DownloadSegment { toggle: t },
            ) => {
                if t != toggle {
                    return Err(AbortCode::TOGGLE);
                }
                self.done = pos;
                if last {
                    return Ok(Some(Vec::new()));
                }
                self.send_download_segment(pos, !toggle, out)?;
                Ok(None)
            }
            (
                State::UploadInit | State::BlockUploadInit,
                Response::InitiateUpload { index, sub, data },
            ) => {
                self.check_mux(index, sub)?;
                self.upload_initiated(data, out)
            }
            (
                State::UploadSegment { toggle, size },
                Response::UploadSegment {
                    toggle: t,
                    last,
                    data,
                },
            ) => {
                if t != toggle {
                    return Err(AbortCode::TOGGLE);
                }
                self.receive(data, size)?;
                if last {
                    if size.is_some_and(|s| self.done != s) {
                        return Err(AbortCode::LENGTH_MISMATCH);
                    }
                    return Ok(Some(self.take_received()));
                }
                out.push(Request::UploadSegment { toggle: !toggle }.write());
                self.state = State::UploadSegment {
                    toggle: !toggle,
                    size,
                };
                Ok(None)
            }
            (
                State::BlockDownloadInit,
                Response::BlockDownload {
                    index,
                    sub,
                    crc,
                    blksize,
                },
            ) => {
                self.check_mux(index, sub)?;
                if !(1..=MAX_BLOCK_SIZE).contains(&blksize) {
                    return Err(AbortCode::BLOCK_SIZE);
                }
                let crc = crc && self.config.crc;
                let sent = self.send_sub_block(0, blksize, out)?;
                self.state = State::BlockDownloadSub {
                    block_start: 0,
                    sent,
                    crc,
                };
                Ok(None)
            }
            (
                State::BlockDownloadSub {
                    block_start,
                    sent,
                    crc,
                },
                Response::BlockDownloadAck { ackseq, blksize },
            ) => {
                let ackseq = u64::from(ackseq);
                let segments_sent = sent.div_ceil(SEGMENT_DATA as u64).max(1);
                if ackseq > segments_sent {
                    return Err(AbortCode::SEQUENCE);
                }
                if !(1..=MAX_BLOCK_SIZE).contains(&blksize) {
                    return Err(AbortCode::BLOCK_SIZE);
                }
                let acked_end = (block_start + ackseq * SEGMENT_DATA as u64).min(len);
                self.done = acked_end;
                if block_start + sent >= len && ackseq == segments_sent {
                    let last_len = len - (block_start + (segments_sent - 1) * SEGMENT_DATA as u64);
                    let end = Request::BlockDownloadEnd {
                        unused: (SEGMENT_DATA as u64 - last_len) as u8,
                        crc: if crc { self.crc.value() } else { 0 },
                    };
                    out.push(end.write());
                    self.state = State::BlockDownloadEnd;
                    return Ok(None);
                }
                // Resume after the last acknowledged segment (repeating what was lost).
                let sent = self.send_sub_block(acked_end, blksize, out)?;
                self.state = State::BlockDownloadSub {
                    block_start: acked_end,
                    sent,
                    crc,
                };
                Ok(None)
            }
            (State::BlockDownloadEnd, Response::BlockDownloadEnd) => Ok(Some(Vec::new())),
            (
                State::BlockUploadInit,
                Response::BlockUpload {
                    index,
                    sub,
                    crc,
                    size,
                },
            ) => {
                self.check_mux(index, sub)?;
                let size = size.map(u64::from);
                self.total = size;
                out.push(Request::BlockUploadStart.write());
                self.state = State::BlockUploadSub(BlockUpload {
                    size,
                    crc: crc && self.config.crc,
                    receiver: SubBlockReceiver::new(self.config.block_size),
                });
                Ok(None)
            }
            (State::BlockUploadEnd(b), Response::BlockUploadEnd { unused, crc }) => {
                self.receive(&b.receiver.tail(unused), b.size)?;
                if b.size.is_some_and(|s| s != self.done) {
                    return Err(AbortCode::LENGTH_MISMATCH);
                }
                if b.crc && self.crc.value() != crc {
                    return Err(AbortCode::CRC);
                }
                out.push(Request::BlockUploadEnd.write());
                Ok(Some(self.take_received()))
            }
            _ => Err(AbortCode::COMMAND),
        }
    }

    /// Take uploaded bytes: count them, check them against the indicated size, run the CRC.
    fn receive(&mut self, data: &[u8], size: Option<u64>) -> Result<(), AbortCode> {
        self.done += data.len() as u64;
        if size.is_some_and(|s| self.done > s) {
            return Err(AbortCode::LENGTH_TOO_HIGH);
        }
        self.crc.update(data);
        self.received.extend_from_slice(data);
        Ok(())
    }

    fn upload_initiated(
        &mut self,
        data: Initiate<'_>,
        out: &mut Vec<Payload>,
    ) -> Result<Option<Vec<u8>>, AbortCode> {
        let size = match data {
            Initiate::Expedited { data, .. } => {
                self.receive(data, None)?;
                return Ok(Some(self.take_received()));
            }
            Initiate::Size(n) => Some(u64::from(n)),
            Initiate::Unsized => None,
        };
        self.total = size;
        out.push(Request::UploadSegment { toggle: false }.write());
        self.state = State::UploadSegment {
            toggle: false,
            size,
        };
        Ok(None)
    }

    /// Read `buf.len()` download bytes at `pos`, keeping the CRC over first-time bytes.
    fn read_source(&mut self, pos: u64, buf: &mut [u8]) -> Result<(), AbortCode> {
        let source = self.source.as_mut().ok_or(AbortCode::GENERAL)?;
        if let Err(e) = source.read_at(pos, buf) {
            tracing::warn!(error = %e, "reading SDO download data failed");
            return Err(AbortCode::GENERAL);
        }
        let end = pos + buf.len() as u64;
        if end > self.crc_pos {
            let skip = (self.crc_pos.saturating_sub(pos)) as usize;
            self.crc.update(&buf[skip..]);
            self.crc_pos = end;
        }
        Ok(())
    }

    fn send_download_segment(
        &mut self,
        pos: u64,
        toggle: bool,
        out: &mut Vec<Payload>,
    ) -> Result<(), AbortCode> {
        let len = self.total.unwrap_or(0);
        let end = (pos + SEGMENT_DATA as u64).min(len);
        let n = (end - pos) as usize;
        let mut data = [0u8; SEGMENT_DATA];
        self.read_source(pos, &mut data[..n])?;
        let last = end == len;
        let segment = Request::DownloadSegment {
            toggle,
            last,
            data: &data[..n],
        };
        out.push(segment.write());
        self.state = State::DownloadSegment {
            pos: end,
            toggle,
            last,
        };
        Ok(())
    }

    /// Send up to `blksize` segments from `start`; returns the bytes covered.
    fn send_sub_block(
        &mut self,
        start: u64,
        blksize: u8,
        out: &mut Vec<Payload>,
    ) -> Result<u64, AbortCode> {
        let len = self.total.unwrap_or(0);
        let mut pos = start;
        for seq in 1..=blksize {
            let end = (pos + SEGMENT_DATA as u64).min(len);
            let mut chunk = [0u8; SEGMENT_DATA];
            let n = (end - pos) as usize;
            self.read_source(pos, &mut chunk[..n])?;
            let last = end == len;
            let data = &chunk[..n];
            out.push(BlockSegment { seq, last, data }.write());
            pos = end;
            if last {
                break;
            }
        }
        Ok(pos - start)
    }

    fn block_upload_segment(
        &mut self,
        mut b: BlockUpload,
        segment: BlockSegment<'_>,
        out: &mut Vec<Payload>,
    ) -> Result<Option<Vec<u8>>, AbortCode> {
        let received = b.receiver.segment(segment)?;
        if let Some(data) = received.data {
            self.receive(data, b.size)?;
        }
        out.extend(received.ack.map(|a| {
            Request::BlockUploadAck {
                ackseq: a.ackseq,
                blksize: a.blksize,
            }
            .write()
        }));
        self.state = if received.complete {
            State::BlockUploadEnd(b)
        } else {
            State::BlockUploadSub(b)
        };
        Ok(None)
    }
}
