//! The SDO frames as types (CiA 301 §7.2.4.3): every request a client sends and every response
//! a server sends, read from and written to the 8-byte payload in one place — for the server,
//! the client and the bus monitor alike.
//!
//! The segments inside a block transfer's sub-block carry no command specifier (their first
//! byte is the sequence number), so they are read with [`BlockSegment::read`] by whoever knows
//! a sub-block is under way; everything else has one reading.

use std::fmt;

use super::abort::AbortCode;
use super::{Payload, SEGMENT_DATA};

/// The data part of an initiate frame (download request, upload response).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Initiate<'a> {
    /// Expedited: the data itself (1–4 bytes when `sized`; all 4 bytes otherwise, the receiver
    /// takes as many as its type needs).
    Expedited {
        /// The data bytes.
        data: &'a [u8],
        /// The frame said how many bytes are data.
        sized: bool,
    },
    /// Segmented with this many bytes to come.
    Size(u32),
    /// Segmented, size not indicated.
    Unsized,
}

/// A client → server SDO frame (except block segments).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Request<'a> {
    /// Initiate download (ccs 1).
    InitiateDownload {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Expedited data or the size.
        data: Initiate<'a>,
    },
    /// Download segment (ccs 0).
    DownloadSegment {
        /// Toggle bit.
        toggle: bool,
        /// No more segments follow.
        last: bool,
        /// 0–7 data bytes.
        data: &'a [u8],
    },
    /// Initiate upload (ccs 2).
    InitiateUpload {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// Upload segment request (ccs 3).
    UploadSegment {
        /// Toggle bit.
        toggle: bool,
    },
    /// Initiate block download (ccs 6, cs 0).
    BlockDownload {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The client supports CRC.
        crc: bool,
        /// Size indicated.
        size: Option<u32>,
    },
    /// End block download (ccs 6, cs 1).
    BlockDownloadEnd {
        /// Bytes of the last segment that carry no data.
        unused: u8,
        /// CRC of all data (0 without CRC).
        crc: u16,
    },
    /// Initiate block upload (ccs 5, cs 0).
    BlockUpload {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The client supports CRC.
        crc: bool,
        /// Segments per block (1–127).
        blksize: u8,
        /// Protocol switch threshold: up to this many bytes by the normal upload (0: never).
        pst: u8,
    },
    /// Start the block upload (ccs 5, cs 3).
    BlockUploadStart,
    /// Acknowledge an upload sub-block (ccs 5, cs 2).
    BlockUploadAck {
        /// Last segment received in sequence.
        ackseq: u8,
        /// Segments per block from now on.
        blksize: u8,
    },
    /// End block upload (ccs 5, cs 1).
    BlockUploadEnd,
    /// Abort transfer (cs 4).
    Abort {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Why.
        code: AbortCode,
    },
}

/// A server → client SDO frame (except block segments).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Response<'a> {
    /// Initiate download response (scs 3).
    InitiateDownload {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
    },
    /// Download segment response (scs 1).
    DownloadSegment {
        /// Toggle bit.
        toggle: bool,
    },
    /// Initiate upload response (scs 2).
    InitiateUpload {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Expedited data or the size.
        data: Initiate<'a>,
    },
    /// Upload segment response (scs 0).
    UploadSegment {
        /// Toggle bit.
        toggle: bool,
        /// No more segments follow.
        last: bool,
        /// 0–7 data bytes.
        data: &'a [u8],
    },
    /// Initiate block download response (scs 5, ss 0).
    BlockDownload {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The server supports CRC.
        crc: bool,
        /// Segments per block (1–127).
        blksize: u8,
    },
    /// Acknowledge a download sub-block (scs 5, ss 2).
    BlockDownloadAck {
        /// Last segment received in sequence.
        ackseq: u8,
        /// Segments per block from now on.
        blksize: u8,
    },
    /// End block download response (scs 5, ss 1).
    BlockDownloadEnd,
    /// Initiate block upload response (scs 6, ss 0).
    BlockUpload {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// The server supports CRC.
        crc: bool,
        /// Size indicated.
        size: Option<u32>,
    },
    /// End block upload (scs 6, ss 1).
    BlockUploadEnd {
        /// Bytes of the last segment that carry no data.
        unused: u8,
        /// CRC of all data (0 without CRC).
        crc: u16,
    },
    /// Abort transfer (cs 4).
    Abort {
        /// Index.
        index: u16,
        /// Sub-index.
        sub: u8,
        /// Why.
        code: AbortCode,
    },
}

/// A segment of a block transfer's sub-block.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BlockSegment<'a> {
    /// Sequence number 1–127 (0 is never a segment: a frame 80h inside a sub-block is an abort).
    pub seq: u8,
    /// The last segment of the transfer.
    pub last: bool,
    /// 7 bytes (the last segment's unused ones are counted by the end frame).
    pub data: &'a [u8],
}

impl<'a> BlockSegment<'a> {
    /// Read a frame known to be a block segment.
    pub fn read(p: &'a Payload) -> BlockSegment<'a> {
        BlockSegment {
            seq: p[0] & 0x7F,
            last: p[0] & 0x80 != 0,
            data: &p[1..8],
        }
    }

    /// Write it (up to 7 data bytes).
    pub fn write(&self) -> Payload {
        let mut p = [0u8; 8];
        p[0] = self.seq | if self.last { 0x80 } else { 0 };
        let n = self.data.len().min(SEGMENT_DATA);
        p[1..1 + n].copy_from_slice(&self.data[..n]);
        p
    }
}

fn u16_at(p: &Payload, at: usize) -> u16 {
    u16::from_le_bytes([p[at], p[at + 1]])
}

fn u32_at(p: &Payload, at: usize) -> u32 {
    u32::from_le_bytes([p[at], p[at + 1], p[at + 2], p[at + 3]])
}

fn mux(p: &Payload) -> (u16, u8) {
    (u16_at(p, 1), p[3])
}

/// A frame with a command byte, the multiplexer and four data bytes.
fn with_mux(command: u8, index: u16, sub: u8, data: [u8; 4]) -> Payload {
    let mut p = [0u8; 8];
    p[0] = command;
    p[1..3].copy_from_slice(&index.to_le_bytes());
    p[3] = sub;
    p[4..8].copy_from_slice(&data);
    p
}

/// The e, s and n bits of an initiate frame and its four data bytes.
fn read_initiate(p: &Payload) -> Initiate<'_> {
    let (expedited, sized) = (p[0] & 2 != 0, p[0] & 1 != 0);
    match (expedited, sized) {
        (true, true) => Initiate::Expedited {
            data: &p[4..8 - usize::from((p[0] >> 2) & 3)],
            sized: true,
        },
        (true, false) => Initiate::Expedited {
            data: &p[4..8],
            sized: false,
        },
        (false, true) => Initiate::Size(u32_at(p, 4)),
        (false, false) => Initiate::Unsized,
    }
}

/// The command bits and data bytes of an initiate frame with specifier `cs`.
fn write_initiate(cs: u8, index: u16, sub: u8, data: Initiate<'_>) -> Payload {
    match data {
        Initiate::Expedited { data, sized } => {
            let n = data.len().min(4);
            let mut d = [0u8; 4];
            d[..n].copy_from_slice(&data[..n]);
            let bits = if sized {
                0x03 | ((4 - n) as u8) << 2
            } else {
                0x02
            };
            with_mux(cs << 5 | bits, index, sub, d)
        }
        Initiate::Size(size) => with_mux(cs << 5 | 0x01, index, sub, size.to_le_bytes()),
        Initiate::Unsized => with_mux(cs << 5, index, sub, [0; 4]),
    }
}

fn segment_frame(first: u8, toggle: bool, last: bool, data: &[u8]) -> Payload {
    let n = data.len().min(SEGMENT_DATA);
    let mut p = [0u8; 8];
    p[0] = first | u8::from(toggle) << 4 | ((SEGMENT_DATA - n) as u8) << 1 | u8::from(last);
    p[1..1 + n].copy_from_slice(&data[..n]);
    p
}

fn segment_data(p: &Payload) -> &[u8] {
    &p[1..8 - usize::from((p[0] >> 1) & 7)]
}

fn abort_frame(index: u16, sub: u8, code: AbortCode) -> Payload {
    with_mux(0x80, index, sub, code.0.to_le_bytes())
}

fn end_frame(first: u8, unused: u8, crc: u16) -> Payload {
    let c = crc.to_le_bytes();
    [first | (unused & 7) << 2, c[0], c[1], 0, 0, 0, 0, 0]
}

impl<'a> Request<'a> {
    /// Read a client frame; an unknown command specifier is [`AbortCode::COMMAND`].
    pub fn read(p: &'a Payload) -> Result<Request<'a>, AbortCode> {
        let (index, sub) = mux(p);
        Ok(match (p[0] >> 5, p[0] & 3) {
            (4, _) => Request::Abort {
                index,
                sub,
                code: AbortCode(u32_at(p, 4)),
            },
            (0, _) => Request::DownloadSegment {
                toggle: p[0] & 0x10 != 0,
                last: p[0] & 1 != 0,
                data: segment_data(p),
            },
            (1, _) => Request::InitiateDownload {
                index,
                sub,
                data: read_initiate(p),
            },
            (2, _) => Request::InitiateUpload { index, sub },
            (3, _) => Request::UploadSegment {
                toggle: p[0] & 0x10 != 0,
            },
            (6, cs) if cs & 1 == 0 => Request::BlockDownload {
                index,
                sub,
                crc: p[0] & 4 != 0,
                size: (p[0] & 2 != 0).then(|| u32_at(p, 4)),
            },
            (6, _) => Request::BlockDownloadEnd {
                unused: (p[0] >> 2) & 7,
                crc: u16_at(p, 1),
            },
            (5, 0) => Request::BlockUpload {
                index,
                sub,
                crc: p[0] & 4 != 0,
                blksize: p[4],
                pst: p[5],
            },
            (5, 3) => Request::BlockUploadStart,
            (5, 2) => Request::BlockUploadAck {
                ackseq: p[1],
                blksize: p[2],
            },
            (5, _) => Request::BlockUploadEnd,
            _ => return Err(AbortCode::COMMAND),
        })
    }

    /// Write it.
    pub fn write(&self) -> Payload {
        match *self {
            Request::InitiateDownload { index, sub, data } => write_initiate(1, index, sub, data),
            Request::DownloadSegment { toggle, last, data } => {
                segment_frame(0x00, toggle, last, data)
            }
            Request::InitiateUpload { index, sub } => with_mux(0x40, index, sub, [0; 4]),
            Request::UploadSegment { toggle } => {
                [0x60 | u8::from(toggle) << 4, 0, 0, 0, 0, 0, 0, 0]
            }
            Request::BlockDownload {
                index,
                sub,
                crc,
                size,
            } => with_mux(
                0xC0 | u8::from(crc) << 2 | u8::from(size.is_some()) << 1,
                index,
                sub,
                size.unwrap_or(0).to_le_bytes(),
            ),
            Request::BlockDownloadEnd { unused, crc } => end_frame(0xC1, unused, crc),
            Request::BlockUpload {
                index,
                sub,
                crc,
                blksize,
                pst,
            } => with_mux(0xA0 | u8::from(crc) << 2, index, sub, [blksize, pst, 0, 0]),
            Request::BlockUploadStart => [0xA3, 0, 0, 0, 0, 0, 0, 0],
            Request::BlockUploadAck { ackseq, blksize } => [0xA2, ackseq, blksize, 0, 0, 0, 0, 0],
            Request::BlockUploadEnd => [0xA1, 0, 0, 0, 0, 0, 0, 0],
            Request::Abort { index, sub, code } => abort_frame(index, sub, code),
        }
    }
}

impl<'a> Response<'a> {
    /// Read a server frame; an unknown command specifier is [`AbortCode::COMMAND`].
    pub fn read(p: &'a Payload) -> Result<Response<'a>, AbortCode> {
        let (index, sub) = mux(p);
        Ok(match (p[0] >> 5, p[0] & 3) {
            (4, _) => Response::Abort {
                index,
                sub,
                code: AbortCode(u32_at(p, 4)),
            },
            (3, _) => Response::InitiateDownload { index, sub },
            (1, _) => Response::DownloadSegment {
                toggle: p[0] & 0x10 != 0,
            },
            (2, _) => Response::InitiateUpload {
                index,
                sub,
                data: read_initiate(p),
            },
            (0, _) => Response::UploadSegment {
                toggle: p[0] & 0x10 != 0,
                last: p[0] & 1 != 0,
                data: segment_data(p),
            },
            (5, 0) => Response::BlockDownload {
                index,
                sub,
                crc: p[0] & 4 != 0,
                blksize: p[4],
            },
            (5, 2) => Response::BlockDownloadAck {
                ackseq: p[1],
                blksize: p[2],
            },
            (5, 1) => Response::BlockDownloadEnd,
            // The initiate response has the size flag in bit 1: only bit 0 is ss.
            (6, ss) if ss & 1 == 0 => Response::BlockUpload {
                index,
                sub,
                crc: p[0] & 4 != 0,
                size: (p[0] & 2 != 0).then(|| u32_at(p, 4)),
            },
            (6, _) => Response::BlockUploadEnd {
                unused: (p[0] >> 2) & 7,
                crc: u16_at(p, 1),
            },
            _ => return Err(AbortCode::COMMAND),
        })
    }

    /// Write it.
    pub fn write(&self) -> Payload {
        match *self {
            Response::InitiateDownload { index, sub } => with_mux(0x60, index, sub, [0; 4]),
            Response::DownloadSegment { toggle } => {
                [0x20 | u8::from(toggle) << 4, 0, 0, 0, 0, 0, 0, 0]
            }
            Response::InitiateUpload { index, sub, data } => write_initiate(2, index, sub, data),
            Response::UploadSegment { toggle, last, data } => {
                segment_frame(0x00, toggle, last, data)
            }
            Response::BlockDownload {
                index,
                sub,
                crc,
                blksize,
            } => with_mux(0xA0 | u8::from(crc) << 2, index, sub, [blksize, 0, 0, 0]),
            Response::BlockDownloadAck { ackseq, blksize } => {
                [0xA2, ackseq, blksize, 0, 0, 0, 0, 0]
            }
            Response::BlockDownloadEnd => [0xA1, 0, 0, 0, 0, 0, 0, 0],
            Response::BlockUpload {
                index,
                sub,
                crc,
                size,
            } => with_mux(
                0xC0 | u8::from(crc) << 2 | u8::from(size.is_some()) << 1,
                index,
                sub,
                size.unwrap_or(0).to_le_bytes(),
            ),
            Response::BlockUploadEnd { unused, crc } => end_frame(0xC1, unused, crc),
            Response::Abort { index, sub, code } => abort_frame(index, sub, code),
        }
    }
}

/// Whether `p` aborts a transfer: command specifier 4 — or, inside a sub-block, where every
/// other frame is a segment, only 80h (sequence 0 is no segment).
pub fn is_abort(p: &Payload, in_subblock: bool) -> bool {
    p[0] == 0x80 || (!in_subblock && p[0] >> 5 == 4)
}

/// The abort frame for `index`/`sub` with `code`, from either side.
pub fn abort(index: u16, sub: u8, code: AbortCode) -> Payload {
    abort_frame(index, sub, code)
}

fn hex(data: &[u8]) -> String {
    data.iter()
        .map(|b| format!("{b:02X}"))
        .collect::<Vec<_>>()
        .join(" ")
}

/// `download 1017:00`, `= E8 03` for expedited data, `, 8 bytes` for an indicated size.
fn show_initiate(
    f: &mut fmt::Formatter<'_>,
    what: &str,
    index: u16,
    sub: u8,
    data: Option<Initiate<'_>>,
) -> fmt::Result {
    write!(f, "{what} {index:04X}:{sub:02X}")?;
    match data {
        Some(Initiate::Expedited { data, .. }) => write!(f, " = {}", hex(data)),
        Some(Initiate::Size(n)) => write!(f, ", {n} bytes"),
        _ => Ok(()),
    }
}

fn show_segment(f: &mut fmt::Formatter<'_>, toggle: bool, last: bool, data: &[u8]) -> fmt::Result {
    let end = if last { " (last)" } else { "" };
    write!(f, "segment t={} {}{end}", u8::from(toggle), hex(data))
}

fn show_block(
    f: &mut fmt::Formatter<'_>,
    download: bool,
    step: &str,
    object: Option<(u16, u8)>,
) -> fmt::Result {
    let dir = if download { "download" } else { "upload" };
    write!(f, "block {dir} {step}")?;
    match object {
        Some((i, s)) => write!(f, " {i:04X}:{s:02X}"),
        None => Ok(()),
    }
}

impl fmt::Display for Request<'_> {
    /// What a bus monitor prints for the frame.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Request::InitiateDownload { index, sub, data } => {
                show_initiate(f, "download", index, sub, Some(data))
            }
            Request::DownloadSegment { toggle, last, data } => show_segment(f, toggle, last, data),
            Request::InitiateUpload { index, sub } => show_initiate(f, "upload", index, sub, None),
            Request::UploadSegment { toggle } => {
                write!(f, "segment ack/request t={}", u8::from(toggle))
            }
            Request::BlockDownload { index, sub, .. } => {
                show_block(f, true, "initiate", Some((index, sub)))
            }
            Request::BlockDownloadEnd { .. } => show_block(f, true, "end", None),
            Request::BlockUpload { index, sub, .. } => {
                show_block(f, false, "initiate", Some((index, sub)))
            }
            Request::BlockUploadStart => show_block(f, false, "start", None),
            Request::BlockUploadAck { .. } => show_block(f, false, "sub-block ack", None),
            Request::BlockUploadEnd => show_block(f, false, "end", None),
            Request::Abort { index, sub, code } => write!(f, "ABORT {index:04X}:{sub:02X} {code}"),
        }
    }
}

impl fmt::Display for Response<'_> {
    /// What a bus monitor prints for the frame.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Response::InitiateDownload { index, sub } => {
                show_initiate(f, "download", index, sub, None)
            }
            Response::DownloadSegment { toggle } => {
                write!(f, "segment ack/request t={}", u8::from(toggle))
            }
            Response::InitiateUpload { index, sub, data } => {
                show_initiate(f, "upload", index, sub, Some(data))
            }
            Response::UploadSegment { toggle, last, data } => show_segment(f, toggle, last, data),
            Response::BlockDownload { index, sub, .. } => {
                show_block(f, true, "initiate", Some((index, sub)))
            }
            Response::BlockDownloadAck { .. } => show_block(f, true, "sub-block ack", None),
            Response::BlockDownloadEnd => show_block(f, true, "end", None),
            Response::BlockUpload { index, sub, .. } => {
                show_block(f, false, "initiate", Some((index, sub)))
            }
            Response::BlockUploadEnd { .. } => show_block(f, false, "end", None),
            Response::Abort { index, sub, code } => write!(f, "ABORT {index:04X}:{sub:02X} {code}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn frames_of_the_specification() {
        // Expedited download of 2 bytes: ccs 1, n 2, e, s.
        let p = [0x2B, 0x17, 0x10, 0x00, 0xE8, 0x03, 0, 0];
        assert_eq!(
            Request::read(&p),
            Ok(Request::InitiateDownload {
                index: 0x1017,
                sub: 0,
                data: Initiate::Expedited {
                    data: &[0xE8, 0x03],
                    sized: true
                }
            })
        );
        assert_eq!(Request::read(&p).unwrap().write(), p);
        assert_eq!(
            Request::read(&p).unwrap().to_string(),
            "download 1017:00 = E8 03"
        );
        // Block upload initiate response with a size.
        let p = [0xC6, 0x00, 0x20, 0x00, 0x00, 0x01, 0, 0];
        assert_eq!(
            Response::read(&p),
            Ok(Response::BlockUpload {
                index: 0x2000,
                sub: 0,
                crc: true,
                size: Some(256)
            })
        );
        assert_eq!(Response::read(&p).unwrap().write(), p);
        assert_eq!(
            Request::read(&[0xE0, 0, 0, 0, 0, 0, 0, 0]),
            Err(AbortCode::COMMAND)
        );
        let abort = abort(0x1008, 0, AbortCode::READ_ONLY);
        let text = Response::read(&abort).unwrap().to_string();
        assert_eq!(text, format!("ABORT 1008:00 {}", AbortCode::READ_ONLY));
        assert!(is_abort(&abort, false) && is_abort(&[0x80; 8], true));
        assert!(!is_abort(&[0x85, 0, 0, 0, 0, 0, 0, 0], true));
    }

    proptest! {
        /// Every frame that reads, writes back to itself (bytes that carry no meaning aside:
        /// reading and writing again gives the same frame).
        #[test]
        fn reading_and_writing_agree(p in any::<[u8; 8]>()) {
            if let Ok(r) = Request::read(&p) {
                let again = r.write();
                prop_assert_eq!(Request::read(&again), Ok(r));
            }
            if let Ok(r) = Response::read(&p) {
                let again = r.write();
                prop_assert_eq!(Response::read(&again), Ok(r));
            }
            let s = BlockSegment::read(&p);
            let written = s.write();
            prop_assert_eq!(BlockSegment::read(&written), s);
        }
    }
}
