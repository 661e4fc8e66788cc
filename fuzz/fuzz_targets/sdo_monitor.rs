//! The bus monitor (`canlift dump`): any frame decoded and explained, SDO transfers tracked
//! across arbitrary frames. No panic.
#![no_main]

use canbus::{CanId, Frame};
use canopen::monitor::{decode, nmt_state_name, SdoTracker};
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let mut tracker = SdoTracker::new();
    let mut rest = data;
    while rest.len() >= 3 {
        let id = u16::from_le_bytes([rest[0], rest[1]]) & 0x7FF;
        let len = usize::from(rest[2] % 9).min(rest.len() - 3);
        let Ok(frame) = Frame::new(CanId::Standard(id), &rest[3..3 + len]) else {
            return;
        };
        rest = &rest[3 + len..];
        let _ = format!("{:?}", decode(&frame));
        let _ = tracker.feed(&frame);
        let _ = nmt_state_name(len as u8);
    }
});
