//! CAN frames (ISO 11898-1 classic CAN), with room for CAN FD.
//!
//! A [`Frame`] is a value type: an identifier, a kind (data, remote, error), up to eight data bytes
//! and an optional receive timestamp. Fields are private so that CAN FD (64 data bytes, BRS/ESI
//! flags) can be added later without breaking users.

use std::fmt;
use std::time::SystemTime;

/// SocketCAN's flag for a 29-bit identifier in a raw `can_id` (`CAN_EFF_FLAG`).
pub const EFF_FLAG: u32 = 0x8000_0000;
/// SocketCAN's flag for a remote transmission request in a raw `can_id` (`CAN_RTR_FLAG`).
pub const RTR_FLAG: u32 = 0x4000_0000;
/// SocketCAN's flag for an error frame in a raw `can_id` (`CAN_ERR_FLAG`).
pub const ERR_FLAG: u32 = 0x2000_0000;

/// Largest 11-bit identifier.
pub const STANDARD_ID_MAX: u16 = 0x7FF;
/// Largest 29-bit identifier.
pub const EXTENDED_ID_MAX: u32 = 0x1FFF_FFFF;
/// Largest data length of a classic CAN frame.
pub const CLASSIC_MAX_LEN: usize = 8;

/// Why a frame or identifier could not be built.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// An 11-bit identifier above 0x7FF.
    #[error("standard CAN identifier 0x{0:X} is above 0x7FF")]
    StandardIdRange(u32),
    /// A 29-bit identifier above 0x1FFFFFFF.
    #[error("extended CAN identifier 0x{0:X} is above 0x1FFFFFFF")]
    ExtendedIdRange(u32),
    /// More than eight data bytes for a classic frame (or a DLC above 8).
    #[error("classic CAN frames carry at most 8 data bytes, not {0}")]
    TooLong(usize),
}

/// An 11-bit (CAN 2.0A) or 29-bit (CAN 2.0B) identifier; always within range.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum CanId {
    /// 11-bit identifier, 0..=0x7FF.
    Standard(u16),
    /// 29-bit identifier, 0..=0x1FFFFFFF.
    Extended(u32),
}

impl CanId {
    /// An 11-bit identifier, checked.
    pub fn standard(id: u16) -> Result<Self, FrameError> {
        if id > STANDARD_ID_MAX {
            return Err(FrameError::StandardIdRange(id.into()));
        }
        Ok(CanId::Standard(id))
    }

    /// A 29-bit identifier, checked.
    pub fn extended(id: u32) -> Result<Self, FrameError> {
        if id > EXTENDED_ID_MAX {
            return Err(FrameError::ExtendedIdRange(id));
        }
        Ok(CanId::Extended(id))
    }

    /// The identifier's numeric value, without format flags.
    pub fn as_raw(self) -> u32 {
        match self {
            CanId::Standard(id) => id.into(),
            CanId::Extended(id) => id,
        }
    }

    /// Whether this is a 29-bit identifier.
    pub fn is_extended(self) -> bool {
        matches!(self, CanId::Extended(_))
    }
}

impl fmt::Display for CanId {
    /// candump style: three hex digits for 11-bit, eight for 29-bit identifiers.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            CanId::Standard(id) => write!(f, "{id:03X}"),
            CanId::Extended(id) => write!(f, "{id:08X}"),
        }
    }
}

/// What a frame is on the wire.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[non_exhaustive]
pub enum FrameKind {
    /// A data frame carrying 0–8 bytes.
    Data,
    /// A remote transmission request; the DLC is requested length, no data travels.
    Remote,
    /// An error frame as reported by a controller (SocketCAN `CAN_ERR_FLAG`); the identifier holds
    /// the error class bits and the data the details (linux/can/error.h).
    Error,
}

/// One classic CAN frame.
#[derive(Clone, Copy, PartialEq, Eq, Hash)]
pub struct Frame {
    id: CanId,
    kind: FrameKind,
    len: u8,
    data: [u8; CLASSIC_MAX_LEN],
    timestamp: Option<SystemTime>,
}

impl Frame {
    /// A data frame with `data` (0–8 bytes).
    pub fn new(id: CanId, data: &[u8]) -> Result<Self, FrameError> {
        if data.len() > CLASSIC_MAX_LEN {
            return Err(FrameError::TooLong(data.len()));
        }
        let mut buf = [0u8; CLASSIC_MAX_LEN];
        buf[..data.len()].copy_from_slice(data);
        Ok(Frame {
            id,
            kind: FrameKind::Data,
            len: data.len() as u8,
            data: buf,
            timestamp: None,
        })
    }

    /// A data frame with an 11-bit identifier; a shorthand for the common CANopen case.
    pub fn standard(id: u16, data: &[u8]) -> Result<Self, FrameError> {
        Self::new(CanId::standard(id)?, data)
    }

    /// A remote transmission request asking for `dlc` bytes.
    pub fn remote(id: CanId, dlc: u8) -> Result<Self, FrameError> {
        if usize::from(dlc) > CLASSIC_MAX_LEN {
            return Err(FrameError::TooLong(dlc.into()));
        }
        Ok(Frame {
            id,
            kind: FrameKind::Remote,
            len: dlc,
            data: [0; CLASSIC_MAX_LEN],
            timestamp: None,
        })
    }

    /// An error frame with the SocketCAN error class in `class` and details in `data`.
    pub fn error(class: u32, data: &[u8]) -> Result<Self, FrameError> {
        let mut frame = Self::new(CanId::extended(class & EXTENDED_ID_MAX)?, data)?;
        frame.kind = FrameKind::Error;
        Ok(frame)
    }

    /// Build a frame from a SocketCAN raw `can_id` (with EFF/RTR/ERR flags) and data.
    pub fn from_raw(raw_id: u32, data: &[u8]) -> Result<Self, FrameError> {
        if raw_id & ERR_FLAG != 0 {
            return Self::error(raw_id & EXTENDED_ID_MAX, data);
        }
        let id = if raw_id & EFF_FLAG != 0 {
            CanId::extended(raw_id & EXTENDED_ID_MAX)?
        } else {
            let id = raw_id & EXTENDED_ID_MAX;
            let short = u16::try_from(id).map_err(|_| FrameError::StandardIdRange(id))?;
            CanId::standard(short)?
        };
        if raw_id & RTR_FLAG != 0 {
            Self::remote(id, data.len() as u8)
        } else {
            Self::new(id, data)
        }
    }

    /// The identifier.
    pub fn id(&self) -> CanId {
        self.id
    }

    /// Data, remote or error frame.
    pub fn kind(&self) -> FrameKind {
        self.kind
    }

    /// Whether this is a remote transmission request.
    pub fn is_remote(&self) -> bool {
        self.kind == FrameKind::Remote
    }

    /// Whether this is an error frame.
    pub fn is_error(&self) -> bool {
        self.kind == FrameKind::Error
    }

    /// The data length code (for a remote frame: the requested length).
    pub fn dlc(&self) -> u8 {
        self.len
    }

    /// The data bytes (empty for a remote frame).
    pub fn data(&self) -> &[u8] {
        match self.kind {
            FrameKind::Remote => &[],
            _ => &self.data[..usize::from(self.len)],
        }
    }

    /// When the frame was received (or sent, for frames that loop back), if known.
    pub fn timestamp(&self) -> Option<SystemTime> {
        self.timestamp
    }

    /// The same frame stamped with `at`.
    pub fn with_timestamp(mut self, at: SystemTime) -> Self {
        self.timestamp = Some(at);
        self
    }

    /// The SocketCAN raw `can_id`: identifier plus EFF/RTR/ERR flags (what filters match on).
    pub fn raw_id(&self) -> u32 {
        let mut raw = self.id.as_raw();
        if self.id.is_extended() && self.kind != FrameKind::Error {
            raw |= EFF_FLAG;
        }
        match self.kind {
            FrameKind::Remote => raw |= RTR_FLAG,
            FrameKind::Error => raw |= ERR_FLAG,
            FrameKind::Data => {}
        }
        raw
    }
}

impl fmt::Debug for Frame {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{self}")
    }
}

impl fmt::Display for Frame {
    /// candump style: `181   [4]  CD 82 01 00`, `701   [0]  remote request`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}   [{}]", self.id, self.len)?;
        match self.kind {
            FrameKind::Remote => return write!(f, "  remote request"),
            FrameKind::Error => write!(f, "  ERRORFRAME")?,
            FrameKind::Data if self.len > 0 => write!(f, " ")?,
            FrameKind::Data => {}
        }
        self.data().iter().try_for_each(|b| write!(f, " {b:02X}"))
    }
}

/// An acceptance filter with SocketCAN semantics: a frame passes when
/// `frame.raw_id() & mask == id & mask`, flags included (so a filter can select 11-bit or
/// 29-bit frames, or remote frames, explicitly).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct Filter {
    /// Raw identifier to compare against, with EFF/RTR flags as wanted.
    pub id: u32,
    /// Which bits of the raw identifier must match.
    pub mask: u32,
}

impl Filter {
    /// Frames with an 11-bit identifier whose bits under `mask` equal those of `id`.
    pub fn standard(id: u16, mask: u16) -> Self {
        Filter {
            id: u32::from(id),
            mask: u32::from(mask) | EFF_FLAG,
        }
    }

    /// Frames with a 29-bit identifier whose bits under `mask` equal those of `id`.
    pub fn extended(id: u32, mask: u32) -> Self {
        Filter {
            id: id | EFF_FLAG,
            mask: mask | EFF_FLAG,
        }
    }

    /// Frames of exactly the identifier `id` (data or remote).
    pub fn exact(id: CanId) -> Self {
        match id {
            CanId::Standard(id) => Filter::standard(id, STANDARD_ID_MAX),
            CanId::Extended(id) => Filter::extended(id, EXTENDED_ID_MAX),
        }
    }

    /// Whether `frame` passes this filter.
    pub fn matches(&self, frame: &Frame) -> bool {
        frame.raw_id() & self.mask == self.id & self.mask
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_filters_take_one_identifier_of_its_kind() {
        let standard = Filter::exact(CanId::Standard(0x181));
        assert!(standard.matches(&Frame::standard(0x181, &[1]).unwrap()));
        assert!(standard.matches(&Frame::remote(CanId::Standard(0x181), 1).unwrap()));
        assert!(!standard.matches(&Frame::standard(0x182, &[1]).unwrap()));
        assert!(!standard.matches(&Frame::new(CanId::Extended(0x181), &[1]).unwrap()));
        let extended = Filter::exact(CanId::Extended(0x1234_5678));
        assert!(extended.matches(&Frame::new(CanId::Extended(0x1234_5678), &[]).unwrap()));
        assert!(!extended.matches(&Frame::new(CanId::Extended(0x1234_5679), &[]).unwrap()));
    }

    #[test]
    fn ids_are_range_checked() {
        assert!(CanId::standard(0x7FF).is_ok());
        assert_eq!(
            CanId::standard(0x800),
            Err(FrameError::StandardIdRange(0x800))
        );
        assert!(CanId::extended(0x1FFF_FFFF).is_ok());
        assert!(CanId::extended(0x2000_0000).is_err());
        assert!(Frame::standard(0x181, &[0; 9]).is_err());
        assert!(Frame::remote(CanId::Standard(1), 9).is_err());
    }

    #[test]
    fn raw_ids_round_trip() {
        let frames = [
            Frame::standard(0x181, &[1, 2]).unwrap(),
            Frame::new(CanId::Extended(0x1234_5678), &[]).unwrap(),
            Frame::remote(CanId::Standard(0x701), 1).unwrap(),
            Frame::remote(CanId::Extended(0x701), 8).unwrap(),
        ];
        for f in frames {
            let back = Frame::from_raw(f.raw_id(), f.data()).unwrap();
            if f.is_remote() {
                assert_eq!(back.id(), f.id());
                assert!(back.is_remote());
            } else {
                assert_eq!(back, f);
            }
        }
        assert_eq!(
            Frame::from_raw(0x800, &[]),
            Err(FrameError::StandardIdRange(0x800))
        );
    }

    #[test]
    fn candump_display() {
        let f = Frame::standard(0x181, &[0xCD, 0x82, 0x01, 0x00]).unwrap();
        assert_eq!(f.to_string(), "181   [4]  CD 82 01 00");
        let r = Frame::remote(CanId::Standard(0x701), 0).unwrap();
        assert_eq!(r.to_string(), "701   [0]  remote request");
        let e = Frame::new(CanId::Extended(0x1ABCDEF), &[0xFF]).unwrap();
        assert_eq!(e.to_string(), "01ABCDEF   [1]  FF");
        let empty = Frame::standard(0x80, &[]).unwrap();
        assert_eq!(empty.to_string(), "080   [0]");
    }

    #[test]
    fn filters_follow_socketcan_semantics() {
        let std = Frame::standard(0x181, &[]).unwrap();
        let ext = Frame::new(CanId::Extended(0x181), &[]).unwrap();
        let tpdo1 = Filter::standard(0x180, 0x780);
        assert!(tpdo1.matches(&std));
        assert!(
            !tpdo1.matches(&ext),
            "an 11-bit filter must not pass 29-bit frames"
        );
        assert!(Filter::extended(0x181, 0x1FFF_FFFF).matches(&ext));
        assert!(!Filter::extended(0x181, 0x1FFF_FFFF).matches(&std));
        let any = Filter { id: 0, mask: 0 };
        assert!(any.matches(&std) && any.matches(&ext));
    }
}
