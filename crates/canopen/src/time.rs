//! TIME (CiA 301 §7.2.6): the TIME_OF_DAY time stamp on COB-ID 0x1012 (default 0x100):
//! milliseconds after midnight (28 bits) and days since 1984-01-01.

use std::time::{Duration, SystemTime, UNIX_EPOCH};

use canbus::{CanId, Frame};

use crate::types::CANOPEN_EPOCH_DAYS;

const MS_PER_DAY: u64 = 86_400_000;

/// Seconds from 1970-01-01 to 1984-01-01.
const EPOCH_OFFSET: Duration = Duration::from_secs(CANOPEN_EPOCH_DAYS as u64 * 86_400);

/// A CANopen time stamp.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct TimeOfDay {
    /// Days since 1984-01-01.
    pub days: u16,
    /// Milliseconds after midnight.
    pub ms: u32,
}

impl TimeOfDay {
    /// The time stamp of a wall-clock instant (`None` before 1984 or after 2163).
    pub fn from_system(t: SystemTime) -> Option<Self> {
        let since = t
            .duration_since(UNIX_EPOCH)
            .ok()?
            .checked_sub(EPOCH_OFFSET)?;
        let ms = u64::try_from(since.as_millis()).ok()?;
        Some(TimeOfDay {
            days: u16::try_from(ms / MS_PER_DAY).ok()?,
            ms: (ms % MS_PER_DAY) as u32,
        })
    }

    /// The wall-clock instant of this time stamp.
    pub fn to_system(self) -> SystemTime {
        UNIX_EPOCH
            + EPOCH_OFFSET
            + Duration::from_millis(u64::from(self.days) * MS_PER_DAY + u64::from(self.ms))
    }

    /// The 6 data bytes.
    pub fn to_bytes(self) -> [u8; 6] {
        let m = (self.ms & 0x0FFF_FFFF).to_le_bytes();
        let d = self.days.to_le_bytes();
        [m[0], m[1], m[2], m[3], d[0], d[1]]
    }

    /// Decode 6 data bytes.
    pub fn parse(data: &[u8]) -> Option<Self> {
        let d: &[u8; 6] = data.try_into().ok()?;
        let ms = u32::from_le_bytes([d[0], d[1], d[2], d[3]]) & 0x0FFF_FFFF;
        (ms < MS_PER_DAY as u32).then_some(TimeOfDay {
            ms,
            days: u16::from_le_bytes([d[4], d[5]]),
        })
    }

    /// The TIME frame (default COB-ID 0x100) carrying this stamp.
    pub fn frame(self, cob_id: CanId) -> Frame {
        Frame::new(cob_id, &self.to_bytes()).unwrap_or_else(|_| unreachable!("6 bytes fit"))
    }
}

/// The default TIME COB-ID.
pub const TIME_COB_ID: CanId = CanId::Standard(0x100);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trips_and_epoch() {
        assert_eq!(
            TimeOfDay::from_system(UNIX_EPOCH + EPOCH_OFFSET),
            Some(TimeOfDay { days: 0, ms: 0 })
        );
        assert_eq!(TimeOfDay::from_system(UNIX_EPOCH), None, "before 1984");
        // 2024-01-01 12:34:56.789 UTC = 1704112496.789 s since 1970.
        let t = UNIX_EPOCH + Duration::from_millis(1_704_112_496_789);
        let stamp = TimeOfDay::from_system(t).unwrap();
        assert_eq!(
            stamp,
            TimeOfDay {
                days: 14610,
                ms: 45_296_789
            }
        );
        assert_eq!(stamp.to_system(), t);
        let f = stamp.frame(TIME_COB_ID);
        assert_eq!(TimeOfDay::parse(f.data()), Some(stamp));
        assert_eq!(
            canopen_monitor_text(&f),
            "TIME 2024-01-01 12:34:56.789",
            "the monitor agrees"
        );
        assert_eq!(
            TimeOfDay::parse(&[0xFF, 0xFF, 0xFF, 0x0F, 0, 0]),
            None,
            "beyond midnight"
        );
    }

    fn canopen_monitor_text(f: &Frame) -> String {
        crate::monitor::decode(f).to_string()
    }
}
