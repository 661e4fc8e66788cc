//! The lift-number rule (CiA 417-4 §4.1.1): lift-control application 1 uses 6000h–67FFh, and
//! application n (up to 8) the same objects shifted by (n − 1) × 800h, up to 9FFFh.

/// Lift-control applications a device can hold.
pub const MAX_LIFTS: u8 = 8;

/// The span of one lift-control application's objects.
pub const LIFT_SPAN: u16 = 0x800;

/// The first index of lift 1's objects.
pub const LIFT1_BASE: u16 = 0x6000;

/// The index of lift-1 object `index` for lift `lift` (1–8); `None` when `index` is not a
/// lift-1 application object or `lift` is out of range.
pub fn for_lift(index: u16, lift: u8) -> Option<u16> {
    if !(LIFT1_BASE..LIFT1_BASE + LIFT_SPAN).contains(&index) || !(1..=MAX_LIFTS).contains(&lift) {
        return None;
    }
    Some(index + u16::from(lift - 1) * LIFT_SPAN)
}

/// Which lift an application object belongs to and its lift-1 index: `(lift, base index)`.
pub fn lift_of(index: u16) -> Option<(u8, u16)> {
    if !(LIFT1_BASE..LIFT1_BASE + LIFT_SPAN * u16::from(MAX_LIFTS)).contains(&index) {
        return None;
    }
    let offset = index - LIFT1_BASE;
    Some((
        (offset / LIFT_SPAN) as u8 + 1,
        LIFT1_BASE + offset % LIFT_SPAN,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn offsets_follow_cia_417() {
        assert_eq!(for_lift(0x6383, 1), Some(0x6383));
        assert_eq!(for_lift(0x6383, 2), Some(0x6B83));
        assert_eq!(for_lift(0x6000, 8), Some(0x9800));
        assert_eq!(for_lift(0x67FF, 8), Some(0x9FFF));
        assert_eq!(for_lift(0x6800, 1), None, "not a lift-1 object");
        assert_eq!(for_lift(0x6383, 9), None);
        assert_eq!(for_lift(0x6383, 0), None);
        assert_eq!(lift_of(0x6B83), Some((2, 0x6383)));
        assert_eq!(lift_of(0x9FFF), Some((8, 0x67FF)));
        assert_eq!(lift_of(0xA000), None);
        assert_eq!(lift_of(0x5022), None);
        for lift in 1..=MAX_LIFTS {
            for index in [0x6000, 0x6383, 0x67FF] {
                assert_eq!(lift_of(for_lift(index, lift).unwrap()), Some((lift, index)));
            }
        }
    }
}
