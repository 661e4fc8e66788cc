//! The socketcand text protocol, sans-IO: an incremental decoder and encoders.
//!
//! socketcand (linux-can/socketcand, `doc/protocol.md`) frames every message as `< word args… >`.
//! Only what a raw-mode session uses is modelled: `hi`, `ok`, `echo`, `open`, the mode switches,
//! `send` (client → server) and `frame` / `error` (server → client). The encoders produce exactly
//! what python-can's `socketcand` interface parses (`len(id) != 3` means a 29-bit identifier; the
//! data field of an empty frame is empty, leaving two spaces before `>`).

use std::fmt::Write as _;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use crate::frame::{CanId, Frame, CLASSIC_MAX_LEN};

/// The longest message accepted, `<` to `>` inclusive. A raw-mode frame needs at most ~60 bytes;
/// anything longer is garbage or an attack, and the stream is not worth resynchronising.
pub const MAX_MESSAGE_LEN: usize = 256;

/// One socketcand message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Message {
    /// `< hi >`: the server's greeting.
    Hi,
    /// `< ok >`: a command succeeded.
    Ok,
    /// `< echo >`: liveness check; the server answers with the same.
    Echo,
    /// `< open CHANNEL >`: attach to a bus.
    Open(String),
    /// `< rawmode >`: switch to raw frame exchange.
    RawMode,
    /// `< bcmmode >`: switch to broadcast-manager mode (not offered by the hub).
    BcmMode,
    /// `< controlmode >` (not offered by the hub).
    ControlMode,
    /// `< isotpmode >` (not offered by the hub).
    IsoTpMode,
    /// `< send ID DLC B0 B1 … >`: a frame for the bus.
    Send(Frame),
    /// `< frame ID SECS.USECS DATA >` or `< error ID SECS.USECS >`: a frame seen on the bus.
    Frame(Frame),
    /// `< error TEXT >`: a command failed.
    Error(String),
}

/// Why bytes could not be decoded into a [`Message`].
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum DecodeError {
    /// Bytes outside any `< … >` were skipped.
    #[error("{0} byte(s) outside any < … > message skipped")]
    Garbage(usize),
    /// A message grew beyond [`MAX_MESSAGE_LEN`] without its closing `>`.
    #[error("message longer than {MAX_MESSAGE_LEN} bytes")]
    Oversized,
    /// A complete message that is not valid; the message is dropped.
    #[error("invalid message {text:?}: {reason}")]
    Invalid {
        /// The message text (truncated for logs).
        text: String,
        /// What is wrong with it.
        reason: &'static str,
    },
}

/// Incremental decoder: feed it bytes as they arrive, take messages out.
#[derive(Debug, Default)]
pub struct Decoder {
    buf: Vec<u8>,
    pos: usize,
}

impl Decoder {
    /// A decoder with an empty buffer.
    pub fn new() -> Self {
        Self::default()
    }

    /// Append received bytes.
    pub fn feed(&mut self, bytes: &[u8]) {
        if self.pos > 0 && self.pos == self.buf.len() {
            self.buf.clear();
            self.pos = 0;
        } else if self.pos > 4096 {
            self.buf.drain(..self.pos);
            self.pos = 0;
        }
        self.buf.extend_from_slice(bytes);
    }

    /// Bytes fed but not yet consumed.
    pub fn pending(&self) -> usize {
        self.buf.len() - self.pos
    }

    /// The next complete message, an error for bad input (already consumed, so calling again
    /// continues after it), or `None` when more bytes are needed.
    ///
    /// After [`DecodeError::Oversized`] the buffer is discarded: the peer is out of step.
    pub fn next_message(&mut self) -> Option<Result<Message, DecodeError>> {
        let rest = &self.buf[self.pos..];
        let skipped = rest.iter().position(|&b| b == b'<').unwrap_or(rest.len());
        let garbage = rest[..skipped]
            .iter()
            .filter(|b| !b.is_ascii_whitespace())
            .count();
        self.pos += skipped;
        if garbage > 0 {
            return Some(Err(DecodeError::Garbage(garbage)));
        }
        let rest = &self.buf[self.pos..];
        if rest.is_empty() {
            return None;
        }
        match rest.iter().position(|&b| b == b'>') {
            Some(end) if end < MAX_MESSAGE_LEN => {
                let result = parse(&rest[..=end]);
                self.pos += end + 1;
                Some(result)
            }
            None if rest.len() < MAX_MESSAGE_LEN => None,
            _ => {
                self.buf.clear();
                self.pos = 0;
                Some(Err(DecodeError::Oversized))
            }
        }
    }
}

fn invalid(raw: &[u8], reason: &'static str) -> DecodeError {
    let text: String = String::from_utf8_lossy(raw).chars().take(80).collect();
    DecodeError::Invalid { text, reason }
}

/// Parse one complete message, `<` … `>` inclusive.
pub fn parse(raw: &[u8]) -> Result<Message, DecodeError> {
    let inner = raw
        .strip_prefix(b"<")
        .and_then(|r| r.strip_suffix(b">"))
        .ok_or_else(|| invalid(raw, "not enclosed in < >"))?;
    let text = std::str::from_utf8(inner).map_err(|_| invalid(raw, "not ASCII"))?;
    let mut words = text.split_ascii_whitespace();
    let word = words.next().ok_or_else(|| invalid(raw, "empty message"))?;
    let args: Vec<&str> = words.collect();
    let bare = |m: Message| {
        if args.is_empty() {
            Ok(m)
        } else {
            Err(invalid(raw, "unexpected arguments"))
        }
    };
    match word {
        "hi" => bare(Message::Hi),
        "ok" => bare(Message::Ok),
        "echo" => bare(Message::Echo),
        "rawmode" => bare(Message::RawMode),
        "bcmmode" => bare(Message::BcmMode),
        "controlmode" => bare(Message::ControlMode),
        "isotpmode" => bare(Message::IsoTpMode),
        "open" => match args.as_slice() {
            [channel] if channel.len() <= 64 => Ok(Message::Open((*channel).to_owned())),
            _ => Err(invalid(raw, "open takes one channel name")),
        },
        "send" => parse_send(&args)
            .map(Message::Send)
            .map_err(|reason| invalid(raw, reason)),
        "frame" => parse_frame(&args)
            .map(Message::Frame)
            .map_err(|reason| invalid(raw, reason)),
        "error" => Ok(parse_error_frame(&args)
            .map(Message::Frame)
            .unwrap_or_else(|| Message::Error(args.join(" ")))),
        _ => Err(invalid(raw, "unknown command")),
    }
}

fn hex_u32(text: &str) -> Option<u32> {
    if text.is_empty() || text.len() > 8 || !text.bytes().all(|b| b.is_ascii_hexdigit()) {
        return None;
    }
    u32::from_str_radix(text, 16).ok()
}

/// socketcand writes 11-bit identifiers with three digits and 29-bit ones with eight; python-can
/// reads any length other than three as 29-bit. We accept 1–3 digits as 11-bit, 4–8 as 29-bit.
fn parse_id(text: &str) -> Result<CanId, &'static str> {
    let value = hex_u32(text).ok_or("identifier is not 1-8 hex digits")?;
    if text.len() <= 3 {
        let id = u16::try_from(value).map_err(|_| "identifier out of range")?;
        CanId::standard(id).map_err(|_| "11-bit identifier above 7FF")
    } else {
        CanId::extended(value).map_err(|_| "29-bit identifier above 1FFFFFFF")
    }
}

fn parse_send(args: &[&str]) -> Result<Frame, &'static str> {
    let [id, dlc, bytes @ ..] = args else {
        return Err("send needs an identifier and a length");
    };
    let id = parse_id(id)?;
    let dlc = hex_u32(dlc).ok_or("length is not hex")? as usize;
    if dlc > CLASSIC_MAX_LEN {
        return Err("length above 8");
    }
    if bytes.len() != dlc {
        return Err("number of data bytes differs from the length");
    }
    let mut data = [0u8; CLASSIC_MAX_LEN];
    for (slot, text) in data.iter_mut().zip(bytes) {
        let value = hex_u32(text).filter(|_| text.len() <= 2);
        *slot = value.ok_or("data byte is not 1-2 hex digits")? as u8;
    }
    Frame::new(id, &data[..dlc]).map_err(|_| "invalid frame")
}

fn parse_timestamp(text: &str) -> Option<SystemTime> {
    let (secs, frac) = text.split_once('.').unwrap_or((text, ""));
    if secs.is_empty()
        || !secs.bytes().all(|b| b.is_ascii_digit())
        || frac.len() > 9
        || !frac.bytes().all(|b| b.is_ascii_digit())
    {
        return None;
    }
    let secs: u64 = secs.parse().ok()?;
    // socketcand's resolution is the microsecond (SECS.USECS): further digits are dropped, so
    // that a frame re-encoded is the frame read.
    let frac = &frac[..frac.len().min(6)];
    let micros = if frac.is_empty() {
        0
    } else {
        frac.parse::<u32>().ok()? * 10u32.pow(6 - frac.len() as u32)
    };
    UNIX_EPOCH.checked_add(Duration::new(secs, micros * 1000))
}

fn parse_frame(args: &[&str]) -> Result<Frame, &'static str> {
    let (id, ts, data) = match args {
        [id, ts] => (id, ts, ""),
        [id, ts, data] => (id, ts, *data),
        _ => return Err("frame needs an identifier, a timestamp and data"),
    };
    let id = parse_id(id)?;
    let at = parse_timestamp(ts).ok_or("timestamp is not SECS.USECS")?;
    if data.len() % 2 != 0 || data.len() > 2 * CLASSIC_MAX_LEN {
        return Err("data is not 0-8 hex bytes");
    }
    let mut bytes = [0u8; CLASSIC_MAX_LEN];
    for (i, pair) in data.as_bytes().chunks(2).enumerate() {
        let pair = std::str::from_utf8(pair).map_err(|_| "data is not hex")?;
        bytes[i] = hex_u32(pair).ok_or("data is not hex")? as u8;
    }
    Frame::new(id, &bytes[..data.len() / 2])
        .map(|f| f.with_timestamp(at))
        .map_err(|_| "invalid frame")
}

/// `< error ID SECS.USECS >`: socketcand's report of an error frame in raw mode.
fn parse_error_frame(args: &[&str]) -> Option<Frame> {
    let [id, ts] = args else { return None };
    if id.len() != 8 {
        return None;
    }
    let class = hex_u32(id)?;
    let at = parse_timestamp(ts)?;
    Frame::error(class, &[]).ok().map(|f| f.with_timestamp(at))
}

/// Append `< send ID DLC B0 … >` for `frame` (data frames only: socketcand's raw mode has no
/// syntax for remote or error frames).
pub fn encode_send(frame: &Frame, out: &mut String) {
    let _ = write!(out, "< send {} {:X} ", frame.id(), frame.dlc());
    for b in frame.data() {
        let _ = write!(out, "{b:02X} ");
    }
    out.push('>');
}

/// Append `< frame ID SECS.USECS DATA >` for `frame` seen at `at`, or `< error CAN_ID
/// SECS.USECS >` for an error frame (the raw `can_id` with the error flag, as socketcand
/// writes it; its syntax carries no error details).
pub fn encode_frame(frame: &Frame, at: SystemTime, out: &mut String) {
    let since = at.duration_since(UNIX_EPOCH).unwrap_or_default();
    if frame.is_error() {
        let _ = write!(
            out,
            "< error {:08X} {}.{:06} >",
            frame.raw_id(),
            since.as_secs(),
            since.subsec_micros()
        );
        return;
    }
    let _ = write!(
        out,
        "< frame {} {}.{:06} ",
        frame.id(),
        since.as_secs(),
        since.subsec_micros()
    );
    for b in frame.data() {
        let _ = write!(out, "{b:02X}");
    }
    out.push_str(" >");
}

/// The text of a message without arguments or with a channel (`< hi >`, `< open can0 >`, …).
pub fn encode_control(message: &Message) -> String {
    match message {
        Message::Hi => "< hi >".into(),
        Message::Ok => "< ok >".into(),
        Message::Echo => "< echo >".into(),
        Message::Open(channel) => format!("< open {channel} >"),
        Message::RawMode => "< rawmode >".into(),
        Message::BcmMode => "< bcmmode >".into(),
        Message::ControlMode => "< controlmode >".into(),
        Message::IsoTpMode => "< isotpmode >".into(),
        Message::Error(text) => format!("< error {text} >"),
        Message::Send(frame) => {
            let mut out = String::new();
            encode_send(frame, &mut out);
            out
        }
        Message::Frame(frame) => {
            let mut out = String::new();
            encode_frame(frame, frame.timestamp().unwrap_or(UNIX_EPOCH), &mut out);
            out
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn decode_all(bytes: &[u8]) -> Vec<Result<Message, DecodeError>> {
        let mut d = Decoder::new();
        d.feed(bytes);
        std::iter::from_fn(|| d.next_message()).collect()
    }

    #[test]
    fn python_can_send_format_is_accepted() {
        // python-can 4.6 writes unpadded lower-case data bytes and a hex length.
        let msgs = decode_all(b"< send 123 3 1 a ff >< send 1FFFFFFF 0  >");
        assert_eq!(
            msgs,
            vec![
                Ok(Message::Send(
                    Frame::standard(0x123, &[1, 0xA, 0xFF]).unwrap()
                )),
                Ok(Message::Send(
                    Frame::new(CanId::Extended(0x1FFF_FFFF), &[]).unwrap()
                )),
            ]
        );
    }

    #[test]
    fn frame_encoding_matches_python_can_expectations() {
        let at = UNIX_EPOCH + Duration::new(1_680_000_000, 123_456_000);
        let mut out = String::new();
        encode_frame(&Frame::standard(0x123, &[]).unwrap(), at, &mut out);
        assert_eq!(out, "< frame 123 1680000000.123456  >");
        out.clear();
        let f = Frame::new(CanId::Extended(0xABC), &[1, 0xFF]).unwrap();
        encode_frame(&f, at, &mut out);
        assert_eq!(out, "< frame 00000ABC 1680000000.123456 01FF >");
    }

    #[test]
    fn bad_input_is_reported_and_skipped() {
        let msgs = decode_all(b"xx< send 800 0 >< send 123 9 >< send 12 2 1 >< hi >");
        assert_eq!(msgs.len(), 5);
        assert_eq!(msgs[0], Err(DecodeError::Garbage(2)));
        assert!(matches!(msgs[1], Err(DecodeError::Invalid { .. })));
        assert!(matches!(msgs[2], Err(DecodeError::Invalid { .. })));
        assert!(matches!(msgs[3], Err(DecodeError::Invalid { .. })));
        assert_eq!(msgs[4], Ok(Message::Hi));
    }

    #[test]
    fn oversized_message_is_reported_once() {
        let mut d = Decoder::new();
        d.feed(b"< send ");
        d.feed(&[b'1'; MAX_MESSAGE_LEN]);
        assert_eq!(d.next_message(), Some(Err(DecodeError::Oversized)));
        assert_eq!(d.next_message(), None);
        d.feed(b"< ok >");
        assert_eq!(d.next_message(), Some(Ok(Message::Ok)));
    }

    #[test]
    fn socketcand_error_messages() {
        assert_eq!(
            decode_all(b"< error could not open bus >"),
            vec![Ok(Message::Error("could not open bus".into()))]
        );
        let msgs = decode_all(b"< error 20000004 12.000001 >");
        // Found by the `socketcand` fuzz target: a timestamp finer than socketcand's microsecond
        // did not survive re-encoding, and an error frame was re-encoded as a data frame.
        for (read, written) in [
            (
                &b"< frame 123 1.0000005 0102 >"[..],
                "< frame 123 1.000000 0102 >",
            ),
            (
                b"< error 20000004 12.000001 >",
                "< error 20000004 12.000001 >",
            ),
        ] {
            let decoded = decode_all(read);
            let Some(Ok(message)) = decoded.first() else {
                panic!("{decoded:?}")
            };
            let text = encode_control(message);
            assert_eq!(text, written);
            assert_eq!(decode_all(text.as_bytes()), decoded);
        }
        let Ok(Message::Frame(f)) = &msgs[0] else {
            panic!("{msgs:?}")
        };
        assert!(f.is_error());
        assert_eq!(f.id().as_raw(), 4);
    }

    fn arb_frame() -> impl Strategy<Value = Frame> {
        let id = prop_oneof![
            (0u16..=0x7FF).prop_map(CanId::Standard),
            (0u32..=0x1FFF_FFFF).prop_map(CanId::Extended),
        ];
        (id, proptest::collection::vec(any::<u8>(), 0..=8))
            .prop_map(|(id, data)| Frame::new(id, &data).unwrap())
    }

    proptest! {
        #[test]
        fn send_round_trips(frame in arb_frame(), split in 0usize..64) {
            let mut text = String::new();
            encode_send(&frame, &mut text);
            let mut d = Decoder::new();
            let split = split.min(text.len());
            d.feed(&text.as_bytes()[..split]);
            let early = d.next_message();
            d.feed(&text.as_bytes()[split..]);
            let got = early.or_else(|| d.next_message());
            prop_assert_eq!(got, Some(Ok(Message::Send(frame))));
        }

        #[test]
        fn frame_round_trips(frame in arb_frame(), secs in 0u64..4_000_000_000, us in 0u32..1_000_000) {
            let at = UNIX_EPOCH + Duration::new(secs, us * 1000);
            let mut text = String::new();
            encode_frame(&frame, at, &mut text);
            let got = decode_all(text.as_bytes());
            prop_assert_eq!(got, vec![Ok(Message::Frame(frame.with_timestamp(at)))]);
        }

        #[test]
        fn arbitrary_bytes_never_panic(chunks in proptest::collection::vec(
            proptest::collection::vec(any::<u8>(), 0..300), 0..8)) {
            let mut d = Decoder::new();
            for chunk in &chunks {
                d.feed(chunk);
                while let Some(result) = d.next_message() {
                    if let Ok(Message::Send(f)) = result {
                        prop_assert!(f.data().len() <= 8);
                    }
                }
                prop_assert!(d.pending() < MAX_MESSAGE_LEN);
            }
        }

        #[test]
        fn arbitrary_text_messages_never_panic(body in "[ -~]{0,80}") {
            let _ = parse(format!("<{body}>").as_bytes());
        }
    }
}
