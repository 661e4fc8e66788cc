//! The CRC of SDO block transfers (CiA 301 §7.2.4.3.16): CRC-16-CCITT, polynomial
//! x^16 + x^12 + x^5 + 1 (0x1021), initial value 0, no reflection, no final XOR
//! (the "XMODEM" parameterisation).

/// A running block-transfer CRC.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Crc16(u16);

const TABLE: [u16; 256] = {
    let mut table = [0u16; 256];
    let mut i = 0;
    while i < 256 {
        let mut crc = (i as u16) << 8;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & 0x8000 != 0 {
                (crc << 1) ^ 0x1021
            } else {
                crc << 1
            };
            bit += 1;
        }
        table[i] = crc;
        i += 1;
    }
    table
};

impl Crc16 {
    /// A CRC over no data (0).
    pub fn new() -> Self {
        Crc16(0)
    }

    /// Continue over `data`.
    pub fn update(&mut self, data: &[u8]) {
        for &b in data {
            self.0 = (self.0 << 8) ^ TABLE[usize::from((self.0 >> 8) as u8 ^ b)];
        }
    }

    /// The CRC so far.
    pub fn value(self) -> u16 {
        self.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn xmodem_check_value() {
        let mut crc = Crc16::new();
        crc.update(b"123456789");
        assert_eq!(crc.value(), 0x31C3);
        let mut split = Crc16::new();
        split.update(b"1234");
        split.update(b"56789");
        assert_eq!(split, crc);
        assert_eq!(Crc16::new().value(), 0);
    }
}
