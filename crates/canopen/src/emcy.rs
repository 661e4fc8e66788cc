//! Emergency objects (CiA 301 §7.2.7): the producer with its error register (0x1001),
//! pre-defined error field (0x1003), COB-ID (0x1014) and inhibit time (0x1015), and the message
//! format consumers decode.

use std::collections::VecDeque;
use std::time::{Duration, Instant};

use canbus::{CanId, Frame};

/// Emergency error codes this stack raises itself (CiA 301 §7.2.7.1, table of error codes).
pub mod codes {
    /// Error reset or no error: the message that ends the errors.
    pub const ERROR_RESET: u16 = 0x0000;
    /// Life guard or heartbeat error (communication).
    pub const HEARTBEAT: u16 = 0x8130;
    /// PDO not processed due to a length error.
    pub const PDO_LENGTH: u16 = 0x8210;
    /// PDO length exceeded.
    pub const PDO_LENGTH_EXCEEDED: u16 = 0x8220;
    /// RPDO timeout.
    pub const RPDO_TIMEOUT: u16 = 0x8250;
}

/// What an emergency error code means (CiA 301 §7.2.7.1, table of error codes), in English
/// and German: the code itself where the table names it, else its class (the most specific
/// of the high byte and the high nibble).
pub fn describe(code: u16) -> (&'static str, &'static str) {
    let exact = match code {
        0x0000 => Some((
            "Error reset or no error",
            "Fehler zurückgesetzt oder kein Fehler",
        )),
        0x8110 => Some((
            "CAN overrun: messages lost",
            "CAN-Überlauf: Nachrichten verloren",
        )),
        0x8120 => Some((
            "CAN in error passive mode",
            "CAN im Zustand „error passive“",
        )),
        0x8130 => Some((
            "Life guard or heartbeat error",
            "Node-Guarding- oder Heartbeat-Fehler",
        )),
        0x8140 => Some(("Recovered from bus off", "Bus-off überwunden")),
        0x8150 => Some(("CAN-ID collision", "CAN-ID-Kollision")),
        0x8210 => Some((
            "PDO not processed: length error",
            "PDO wegen Längenfehler nicht verarbeitet",
        )),
        0x8220 => Some(("PDO length exceeded", "PDO-Länge überschritten")),
        0x8230 => Some((
            "MPDO destination not available",
            "MPDO-Zielobjekt nicht vorhanden",
        )),
        0x8240 => Some(("Unexpected SYNC data length", "Unerwartete SYNC-Datenlänge")),
        0x8250 => Some(("RPDO timeout", "RPDO-Zeitüberschreitung")),
        _ => None,
    };
    let class = || match code >> 8 {
        0x21 => ("Current, device input side", "Strom, Geräteeingang"),
        0x22 => ("Current inside the device", "Strom im Gerät"),
        0x23 => ("Current, device output side", "Strom, Geräteausgang"),
        0x31 => ("Mains voltage", "Netzspannung"),
        0x32 => ("Voltage inside the device", "Spannung im Gerät"),
        0x33 => ("Output voltage", "Ausgangsspannung"),
        0x41 => ("Ambient temperature", "Umgebungstemperatur"),
        0x42 => ("Device temperature", "Gerätetemperatur"),
        0x61 => ("Internal software", "Interne Software"),
        0x62 => ("User software", "Anwendersoftware"),
        0x63 => ("Data set", "Datensatz"),
        0x81 => ("Communication", "Kommunikation"),
        0x82 => ("Protocol error", "Protokollfehler"),
        0xF0 => ("Additional functions", "Zusatzfunktionen"),
        0xFF => ("Device specific", "Gerätespezifisch"),
        _ => match code >> 12 {
            0x1 => ("Generic error", "Allgemeiner Fehler"),
            0x2 => ("Current", "Strom"),
            0x3 => ("Voltage", "Spannung"),
            0x4 => ("Temperature", "Temperatur"),
            0x5 => ("Device hardware", "Gerätehardware"),
            0x6 => ("Device software", "Gerätesoftware"),
            0x7 => ("Additional modules", "Zusatzmodule"),
            0x8 => ("Monitoring", "Überwachung"),
            0x9 => ("External error", "Externer Fehler"),
            _ => ("Unknown error code", "Unbekannter Fehlercode"),
        },
    };
    exact.unwrap_or_else(class)
}

/// One EMCY message.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct EmcyMessage {
    /// Emergency error code (0x0000: error reset / no error).
    pub code: u16,
    /// Error register (0x1001) at the time.
    pub register: u8,
    /// Manufacturer-specific error field.
    pub manufacturer: [u8; 5],
}

impl EmcyMessage {
    /// The 8 data bytes.
    pub fn to_bytes(&self) -> [u8; 8] {
        let c = self.code.to_le_bytes();
        let m = self.manufacturer;
        [c[0], c[1], self.register, m[0], m[1], m[2], m[3], m[4]]
    }

    /// Decode 8 data bytes.
    pub fn parse(data: &[u8]) -> Option<Self> {
        let d: &[u8; 8] = data.try_into().ok()?;
        Some(EmcyMessage {
            code: u16::from_le_bytes([d[0], d[1]]),
            register: d[2],
            manufacturer: [d[3], d[4], d[5], d[6], d[7]],
        })
    }

    /// The producing node of an EMCY frame in the pre-defined connection set (0x081–0x0FF).
    pub fn from_frame(frame: &Frame) -> Option<(u8, Self)> {
        match frame.id() {
            CanId::Standard(id @ 0x81..=0xFF) => {
                Some(((id - 0x80) as u8, Self::parse(frame.data())?))
            }
            _ => None,
        }
    }
}

/// Error register bits (0x1001) for an error code, by the code's class (CiA 301 tables 49/50):
/// bit 0 is set for every error; current, voltage, temperature, communication and
/// device-specific classes add their own bit.
pub fn register_bits(code: u16) -> u8 {
    let class = match code >> 12 {
        0x2 => 1 << 1,
        0x3 => 1 << 2,
        0x4 => 1 << 3,
        0x8 => 1 << 4,
        _ if code >> 8 == 0xFF => 1 << 7,
        _ => 0,
    };
    class | 1
}

/// Entries the pre-defined error field keeps (0x1003 sub-indices 1–254 at most).
pub const MAX_HISTORY: usize = 254;

/// The EMCY producer of one node.
#[derive(Debug, Clone)]
pub struct EmcyProducer {
    cob_id: Option<CanId>,
    inhibit: Duration,
    last_sent: Option<Instant>,
    queue: VecDeque<EmcyMessage>,
    /// Active errors: code and manufacturer field.
    active: Vec<(u16, [u8; 5])>,
    /// Error codes with their manufacturer info, newest first (0x1003 sub 1 is the newest).
    history: VecDeque<u32>,
    history_len: usize,
}

impl EmcyProducer {
    /// A producer for `node_id` on the default COB-ID 0x80 + node-ID, no inhibit time.
    pub fn new(node_id: u8) -> Self {
        EmcyProducer {
            cob_id: Some(CanId::Standard(0x80 + u16::from(node_id & 0x7F))),
            inhibit: Duration::ZERO,
            last_sent: None,
            queue: VecDeque::new(),
            active: Vec::new(),
            history: VecDeque::new(),
            history_len: 8,
        }
    }

    /// Apply 0x1014 (bit 31 set: EMCY not sent; bit 29: 29-bit identifier).
    pub fn set_cob_id(&mut self, value: u32) {
        self.cob_id = crate::cob::id_from_parameter(value);
    }

    /// Apply 0x1015 (multiples of 100 µs).
    pub fn set_inhibit_100us(&mut self, units: u16) {
        self.inhibit = Duration::from_micros(u64::from(units) * 100);
    }

    /// How many entries 0x1003 keeps (1–254).
    pub fn set_history_len(&mut self, len: usize) {
        self.history_len = len.clamp(1, MAX_HISTORY);
        self.history.truncate(self.history_len);
    }

    /// The error register (0x1001) as the active errors make it.
    pub fn error_register(&self) -> u8 {
        self.active
            .iter()
            .fold(0, |r, (code, _)| r | register_bits(*code))
    }

    /// The pre-defined error field entries, newest first (code in bits 0–15, manufacturer
    /// information in bits 16–31).
    pub fn history(&self) -> impl Iterator<Item = u32> + '_ {
        self.history.iter().copied()
    }

    /// Writing 0 to 0x1003 sub 0 clears the history.
    pub fn clear_history(&mut self) {
        self.history.clear();
    }

    /// Whether `code` is active.
    pub fn is_active(&self, code: u16) -> bool {
        self.active.iter().any(|(c, _)| *c == code)
    }

    /// Raise an error: it becomes active, enters the history and an EMCY is queued. Raising an
    /// active error again does nothing.
    pub fn set_error(&mut self, code: u16, manufacturer: [u8; 5]) {
        if code == 0 || self.is_active(code) {
            return;
        }
        self.active.push((code, manufacturer));
        let info = u32::from(u16::from_le_bytes([manufacturer[0], manufacturer[1]]));
        self.history.push_front(u32::from(code) | info << 16);
        self.history.truncate(self.history_len);
        self.queue.push_back(EmcyMessage {
            code,
            register: self.error_register(),
            manufacturer,
        });
    }

    /// Clear an error; when the last one clears, an error-reset EMCY (code 0) is queued.
    pub fn clear_error(&mut self, code: u16) {
        let before = self.active.len();
        self.active.retain(|(c, _)| *c != code);
        if before != self.active.len() && self.active.is_empty() {
            self.queue.push_back(EmcyMessage {
                code: 0,
                register: 0,
                manufacturer: [0; 5],
            });
        }
    }

    /// When [`Self::handle_timeout`] can send the next queued message.
    pub fn poll_timeout(&self) -> Option<Instant> {
        if self.queue.is_empty() {
            return None;
        }
        Some(
            self.last_sent
                .map_or_else(Instant::now, |t| t + self.inhibit),
        )
    }

    /// Send the queued EMCY messages the inhibit time lets through: all of them without an
    /// inhibit time, else the next one. (Messages wait in the queue; none is lost to the
    /// inhibit time.)
    pub fn handle_timeout(&mut self, now: Instant, out: &mut Vec<Frame>) {
        while self.last_sent.is_none_or(|t| now >= t + self.inhibit) {
            let Some(message) = self.queue.pop_front() else {
                return;
            };
            let Some(id) = self.cob_id else {
                // EMCY disabled by 0x1014 bit 31: the history is kept, nothing is sent.
                continue;
            };
            self.last_sent = Some(now);
            out.extend(Frame::new(id, &message.to_bytes()).ok());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_are_described_by_the_most_specific_entry() {
        assert_eq!(describe(0x8130).0, "Life guard or heartbeat error");
        assert_eq!(describe(0x2310).0, "Current, device output side");
        assert_eq!(describe(0x2000).0, "Current");
        assert_eq!(describe(0x5530).1, "Gerätehardware");
        assert_eq!(describe(0xFF42).0, "Device specific");
        assert_eq!(describe(0xA000).0, "Unknown error code");
    }

    /// What one call sends (the tests expect at most one frame at a time).
    fn next(p: &mut EmcyProducer, now: Instant) -> Option<Frame> {
        let mut out = Vec::new();
        p.handle_timeout(now, &mut out);
        assert!(out.len() <= 1, "{out:?}");
        out.pop()
    }

    #[test]
    fn errors_register_history_and_reset() {
        let now = Instant::now();
        let mut p = EmcyProducer::new(1);
        p.set_error(0x8130, [0, 12, 0, 0, 0]);
        assert_eq!(p.error_register(), 0x11, "generic + communication");
        let f = next(&mut p, now).unwrap();
        assert_eq!(
            f,
            Frame::standard(0x081, &[0x30, 0x81, 0x11, 0, 12, 0, 0, 0]).unwrap()
        );
        p.set_error(0x8130, [0, 12, 0, 0, 0]);
        assert!(next(&mut p, now).is_none(), "already active");
        p.set_error(0x4210, [0; 5]);
        assert_eq!(p.error_register(), 0x19, "+ temperature");
        assert_eq!(p.history().collect::<Vec<_>>(), vec![0x4210, 0x0C00_8130]);
        next(&mut p, now);
        p.clear_error(0x8130);
        assert!(
            next(&mut p, now).is_none(),
            "another error still active: no reset yet"
        );
        p.clear_error(0x4210);
        let reset = next(&mut p, now).unwrap();
        assert_eq!(reset.data(), &[0; 8]);
        assert_eq!(p.error_register(), 0);
        p.clear_history();
        assert_eq!(p.history().count(), 0);
    }

    #[test]
    fn inhibit_time_delays_but_never_drops() {
        let t0 = Instant::now();
        let mut p = EmcyProducer::new(2);
        p.set_inhibit_100us(100); // 10 ms
        p.set_error(0x1000, [0; 5]);
        p.set_error(0x2000, [0; 5]);
        assert!(next(&mut p, t0).is_some());
        assert!(next(&mut p, t0 + Duration::from_millis(9)).is_none());
        assert_eq!(p.poll_timeout(), Some(t0 + Duration::from_millis(10)));
        let second = next(&mut p, t0 + Duration::from_millis(10)).unwrap();
        assert_eq!(EmcyMessage::parse(second.data()).unwrap().code, 0x2000);
        assert_eq!(p.poll_timeout(), None);
    }

    #[test]
    fn cob_id_and_history_length() {
        let now = Instant::now();
        let mut p = EmcyProducer::new(3);
        p.set_cob_id(0x2000_0083);
        p.set_error(0xFF01, [0; 5]);
        assert_eq!(p.error_register(), 0x81, "device specific");
        assert_eq!(next(&mut p, now).unwrap().id(), CanId::Extended(0x83));
        p.set_cob_id(0x8000_0083);
        p.set_error(0x5000, [0; 5]);
        assert!(
            next(&mut p, now + Duration::from_secs(1)).is_none(),
            "disabled"
        );
        p.set_history_len(1);
        assert_eq!(p.history().collect::<Vec<_>>(), vec![0x5000]);
        let f = Frame::standard(
            0x083,
            &EmcyMessage {
                code: 0x5000,
                register: 1,
                manufacturer: [1, 2, 3, 4, 5],
            }
            .to_bytes(),
        )
        .unwrap();
        assert_eq!(EmcyMessage::from_frame(&f).unwrap().0, 3);
        assert!(EmcyMessage::from_frame(&Frame::standard(0x080, &[0; 8]).unwrap()).is_none());
    }
}
