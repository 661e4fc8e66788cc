//! How long a frame occupies a classic CAN bus, and who wins arbitration (ISO 11898-1).
//!
//! The frame's bits are built exactly as a controller sends them (SOF, arbitration field, control
//! field, data, CRC-15 over all of those), bit stuffing is counted on that real bit sequence, and
//! the unstuffed tail (CRC delimiter, ACK slot and delimiter, 7-bit EOF, 3-bit intermission) is
//! added. The result is what a bus analyser measures from SOF to the end of the interframe space.

use std::time::Duration;

use crate::frame::{CanId, Frame, FrameKind};

/// CRC-15/CAN generator polynomial x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1.
const CRC15_POLY: u16 = 0x4599;

/// Bits after the CRC sequence that are never stuffed: CRC delimiter (1), ACK slot (1),
/// ACK delimiter (1), end of frame (7), intermission (3).
const UNSTUFFED_TAIL_BITS: u32 = 1 + 1 + 1 + 7 + 3;

/// A growable bit sequence, most significant bit first, as the bus sends it.
struct Bits {
    bits: [bool; 160],
    len: usize,
}

impl Bits {
    fn new() -> Self {
        Bits {
            bits: [false; 160],
            len: 0,
        }
    }

    fn push(&mut self, value: u32, width: u32) {
        for i in (0..width).rev() {
            self.bits[self.len] = (value >> i) & 1 == 1;
            self.len += 1;
        }
    }

    fn as_slice(&self) -> &[bool] {
        &self.bits[..self.len]
    }
}

fn crc15(bits: &[bool]) -> u16 {
    let mut crc: u16 = 0;
    for &bit in bits {
        let top = (crc >> 14) & 1 == 1;
        crc = (crc << 1) & 0x7FFF;
        if top != bit {
            crc ^= CRC15_POLY;
        }
    }
    crc
}

/// Stuff bits a transmitter inserts into `bits`: after five equal bits, one of the opposite
/// level, which itself counts towards the next run.
fn stuff_bit_count(bits: &[bool]) -> u32 {
    let mut count = 0;
    let mut run = 0;
    let mut last = None;
    for &bit in bits {
        if Some(bit) == last {
            run += 1;
        } else {
            last = Some(bit);
            run = 1;
        }
        if run == 5 {
            count += 1;
            last = Some(!bit);
            run = 1;
        }
    }
    count
}

/// The number of bit times `frame` occupies on the bus, SOF to end of interframe space.
pub fn frame_bits(frame: &Frame) -> u32 {
    let remote = frame.kind() == FrameKind::Remote;
    let mut bits = Bits::new();
    bits.push(0, 1); // SOF
    match frame.id() {
        CanId::Standard(id) => {
            bits.push(id.into(), 11);
            bits.push(remote.into(), 1); // RTR
            bits.push(0, 1); // IDE
            bits.push(0, 1); // r0
        }
        CanId::Extended(id) => {
            bits.push(id >> 18, 11);
            bits.push(1, 1); // SRR
            bits.push(1, 1); // IDE
            bits.push(id & 0x3FFFF, 18);
            bits.push(remote.into(), 1); // RTR
            bits.push(0, 2); // r1, r0
        }
    }
    bits.push(frame.dlc().into(), 4);
    for &byte in frame.data() {
        bits.push(byte.into(), 8);
    }
    let crc = crc15(bits.as_slice());
    bits.push(crc.into(), 15);
    bits.len as u32 + stuff_bit_count(bits.as_slice()) + UNSTUFFED_TAIL_BITS
}

/// How long `frame` occupies a bus running at `bitrate` bit/s.
pub fn frame_duration(frame: &Frame, bitrate: u32) -> Duration {
    let nanos = u64::from(frame_bits(frame)) * 1_000_000_000 / u64::from(bitrate.max(1));
    Duration::from_nanos(nanos)
}

/// The arbitration priority of `frame`: lower wins. It is the arbitration field read as a
/// binary number, dominant (0) bits first, so an 11-bit data frame beats the remote frame and any
/// 29-bit frame with the same base identifier (RTR and SRR/IDE decide), as on a real bus.
pub fn arbitration_key(frame: &Frame) -> u32 {
    let remote = u32::from(frame.kind() == FrameKind::Remote);
    match frame.id() {
        CanId::Standard(id) => (u32::from(id) << 21) | (remote << 20),
        CanId::Extended(id) => (id >> 18) << 21 | 1 << 20 | 1 << 19 | (id & 0x3FFFF) << 1 | remote,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crc15_check_value() {
        // CRC-15/CAN check value for the ASCII string "123456789".
        let mut bits = Bits::new();
        for b in b"123456789" {
            bits.push((*b).into(), 8);
        }
        assert_eq!(crc15(bits.as_slice()), 0x059E);
    }

    #[test]
    fn stuffing_counts_inserted_bits() {
        assert_eq!(stuff_bit_count(&[false; 5]), 1);
        assert_eq!(stuff_bit_count(&[false; 9]), 1);
        assert_eq!(stuff_bit_count(&[false; 10]), 2);
        let stuff_then_four_ones = [false, false, false, false, false, true, true, true, true];
        assert_eq!(
            stuff_bit_count(&stuff_then_four_ones),
            2,
            "the stuff bit starts the next run"
        );
        assert_eq!(stuff_bit_count(&[true, false, true, false]), 0);
    }

    #[test]
    fn frame_lengths_are_within_the_textbook_bounds() {
        // Unstuffed: 47 + 8n bits (11-bit), 67 + 8n (29-bit), incl. 3-bit intermission.
        for n in 0..=8usize {
            let data = vec![0x55u8; n];
            let std = Frame::standard(0x2AA, &data).unwrap();
            let bits = frame_bits(&std);
            let base = 47 + 8 * n as u32;
            assert!(
                bits >= base && bits <= base + (34 + 8 * n as u32 - 1) / 4,
                "{n}: {bits}"
            );
            let ext = Frame::new(CanId::Extended(0x0AAA_AAAA), &data).unwrap();
            let bits = frame_bits(&ext);
            let base = 67 + 8 * n as u32;
            assert!(
                bits >= base && bits <= base + (54 + 8 * n as u32 - 1) / 4,
                "{n}: {bits}"
            );
        }
    }

    #[test]
    fn all_zero_data_stuffs_heavily() {
        let zeros = Frame::standard(0, &[0; 8]).unwrap();
        let alternating = Frame::standard(0x555, &[0x55; 8]).unwrap();
        assert!(frame_bits(&zeros) > frame_bits(&alternating) + 10);
        assert_eq!(
            frame_duration(&alternating, 1_000_000),
            Duration::from_micros(frame_bits(&alternating).into())
        );
    }

    #[test]
    fn arbitration_follows_the_bus() {
        let d = |id| Frame::standard(id, &[]).unwrap();
        let r = |id| Frame::remote(CanId::Standard(id), 0).unwrap();
        let x = |id| Frame::new(CanId::Extended(id), &[]).unwrap();
        assert!(arbitration_key(&d(0x100)) < arbitration_key(&d(0x101)));
        assert!(arbitration_key(&d(0x100)) < arbitration_key(&r(0x100)));
        assert!(arbitration_key(&r(0x100)) < arbitration_key(&x(0x100 << 18)));
        assert!(arbitration_key(&x(0x0FF << 18 | 0x3FFFF)) < arbitration_key(&d(0x100)));
        assert!(arbitration_key(&x(5)) < arbitration_key(&x(6)));
    }
}
