//! Errors of the connector: CiA 301 abort codes (NXg SW003 §8.6) with their messages in English
//! and German, and the JSON-RPC 2.0 codes of messages that are not valid requests
//! (docs/PROTOCOL.md §Errors).

use std::fmt;

/// A CiA 301 abort code as the connector carries it in an error's `code` (NXg SW003 §8.6).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct ErrorCode(pub u32);

impl ErrorCode {
    /// No error.
    pub const NO_ERROR: ErrorCode = ErrorCode(0x0000_0000);
    /// Toggle bit not alternated.
    pub const TOGGLE: ErrorCode = ErrorCode(0x0503_0000);
    /// SDO protocol timed out (the bus did not answer).
    pub const TIMEOUT: ErrorCode = ErrorCode(0x0504_0000);
    /// Command specifier not valid or unknown.
    pub const COMMAND: ErrorCode = ErrorCode(0x0504_0001);
    /// Out of memory (also: too many subscriptions).
    pub const OUT_OF_MEMORY: ErrorCode = ErrorCode(0x0504_0005);
    /// Unsupported access to an object.
    pub const UNSUPPORTED_ACCESS: ErrorCode = ErrorCode(0x0601_0000);
    /// Attempt to read a write-only object.
    pub const WRITE_ONLY: ErrorCode = ErrorCode(0x0601_0001);
    /// Attempt to write a read-only object (also: a write the gateway's policy refuses).
    pub const READ_ONLY: ErrorCode = ErrorCode(0x0601_0002);
    /// Object does not exist in the object dictionary.
    pub const NO_OBJECT: ErrorCode = ErrorCode(0x0602_0000);
    /// General parameter incompatibility.
    pub const INCOMPATIBLE: ErrorCode = ErrorCode(0x0604_0043);
    /// Data type (or physical unit) does not match.
    pub const TYPE_MISMATCH: ErrorCode = ErrorCode(0x0607_0010);
    /// Data type does not match, too long (strings, tokens).
    pub const TOO_LONG: ErrorCode = ErrorCode(0x0607_0012);
    /// Data type does not match, too short.
    pub const TOO_SHORT: ErrorCode = ErrorCode(0x0607_0013);
    /// Sub-index does not exist.
    pub const NO_SUB_INDEX: ErrorCode = ErrorCode(0x0609_0011);
    /// Invalid value for the parameter.
    pub const INVALID_VALUE: ErrorCode = ErrorCode(0x0609_0030);
    /// Value written too high.
    pub const TOO_HIGH: ErrorCode = ErrorCode(0x0609_0031);
    /// Value written too low.
    pub const TOO_LOW: ErrorCode = ErrorCode(0x0609_0032);
    /// Maximum value is less than minimum value.
    pub const MAX_BELOW_MIN: ErrorCode = ErrorCode(0x0609_0036);
    /// Cannot be transferred or stored: wrong serial number or password hash (NXg §5.4, §6.4).
    pub const IDENTITY: ErrorCode = ErrorCode(0x0800_0020);
    /// Cannot be transferred or stored because of local control: privilege too low, or an
    /// "engineer on site" object (NXg §6.3, §6.4).
    pub const PRIVILEGE: ErrorCode = ErrorCode(0x0800_0021);
    /// Cannot be transferred or stored because of the present device state (elevation locked
    /// out after wrong password hashes).
    pub const DEVICE_STATE: ErrorCode = ErrorCode(0x0800_0022);
    /// No data available.
    pub const NO_DATA: ErrorCode = ErrorCode(0x0800_0024);
    /// General error.
    pub const GENERAL: ErrorCode = ErrorCode(0x0800_0000);

    /// Every code this module has a message for.
    pub const KNOWN: [ErrorCode; 23] = [
        Self::NO_ERROR,
        Self::TOGGLE,
        Self::TIMEOUT,
        Self::COMMAND,
        Self::OUT_OF_MEMORY,
        Self::UNSUPPORTED_ACCESS,
        Self::WRITE_ONLY,
        Self::READ_ONLY,
        Self::NO_OBJECT,
        Self::INCOMPATIBLE,
        Self::TYPE_MISMATCH,
        Self::TOO_LONG,
        Self::TOO_SHORT,
        Self::NO_SUB_INDEX,
        Self::INVALID_VALUE,
        Self::TOO_HIGH,
        Self::TOO_LOW,
        Self::MAX_BELOW_MIN,
        Self::IDENTITY,
        Self::PRIVILEGE,
        Self::DEVICE_STATE,
        Self::NO_DATA,
        Self::GENERAL,
    ];

    /// The message for this code in `lang` (English and German; other languages get English).
    pub fn message(self, lang: &str) -> &'static str {
        let (en, de) = match self.0 {
            0x0000_0000 => (
                "No error, everything is fine.",
                "Kein Fehler, alles in Ordnung.",
            ),
            0x0503_0000 => ("Toggle bit not alternated.", "Toggle-Bit nicht gewechselt."),
            0x0504_0000 => (
                "SDO protocol timed out.",
                "Zeitüberschreitung im SDO-Protokoll.",
            ),
            0x0504_0001 => (
                "Client/server command specifier not valid or unknown.",
                "Client/Server-Kommando ungültig oder unbekannt.",
            ),
            0x0504_0005 => ("Out of memory.", "Kein Speicher mehr."),
            0x0601_0000 => (
                "Unsupported access to an object.",
                "Nicht unterstützter Zugriff auf ein Objekt.",
            ),
            0x0601_0001 => (
                "Attempt to read a write only object.",
                "Versuch, ein nur schreibbares Objekt zu lesen.",
            ),
            0x0601_0002 => (
                "Attempt to write a read only object.",
                "Versuch, ein nur lesbares Objekt zu schreiben.",
            ),
            0x0602_0000 => (
                "Object does not exist in the object dictionary.",
                "Objekt existiert nicht im Objektverzeichnis.",
            ),
            0x0604_0043 => (
                "General parameter incompatibility reason.",
                "Allgemeine Parameter-Unverträglichkeit.",
            ),
            0x0607_0010 => (
                "Data type does not match, length of param. does not match.",
                "Datentyp oder Einheit passen nicht, Länge des Parameters passt nicht.",
            ),
            0x0607_0012 => (
                "Data type does not match, length of service param. too high.",
                "Datentyp passt nicht, Parameter zu lang.",
            ),
            0x0607_0013 => (
                "Data type does not match, length of service parameter too low.",
                "Datentyp passt nicht, Parameter zu kurz.",
            ),
            0x0609_0011 => ("Sub-index does not exist.", "Subindex existiert nicht."),
            0x0609_0030 => (
                "Invalid value for parameter.",
                "Ungültiger Wert für den Parameter.",
            ),
            0x0609_0031 => (
                "Value of parameter written too high.",
                "Geschriebener Wert zu hoch.",
            ),
            0x0609_0032 => (
                "Value of parameter written too low.",
                "Geschriebener Wert zu niedrig.",
            ),
            0x0609_0036 => (
                "Maximum value is less than minimum value.",
                "Maximalwert ist kleiner als Minimalwert.",
            ),
            0x0800_0020 => (
                "Data cannot be transferred or stored to the application.",
                "Daten können nicht übertragen oder gespeichert werden.",
            ),
            0x0800_0021 => (
                "Data cannot be transferred or stored because of local control.",
                "Daten können wegen lokaler Steuerung nicht übertragen oder gespeichert werden.",
            ),
            0x0800_0022 => (
                "Data cannot be transferred or stored because of the present device state.",
                "Daten können wegen des aktuellen Gerätezustands nicht übertragen oder gespeichert werden.",
            ),
            0x0800_0024 => ("No data available.", "Keine Daten verfügbar."),
            _ => ("General error.", "Allgemeiner Fehler."),
        };
        if lang.eq_ignore_ascii_case("de") {
            de
        } else {
            en
        }
    }
}

impl fmt::Display for ErrorCode {
    /// The hex form of CiA 301: `06020000h`.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:08X}h", self.0)
    }
}

#[cfg(feature = "gateway")]
impl From<canopen::sdo::abort::AbortCode> for ErrorCode {
    fn from(code: canopen::sdo::abort::AbortCode) -> ErrorCode {
        ErrorCode(code.0)
    }
}

/// JSON-RPC 2.0 error codes for messages that are not valid requests (docs/PROTOCOL.md
/// §Errors).
pub mod rpc_codes {
    /// Invalid JSON.
    pub const PARSE: i64 = -32700;
    /// Not a valid request object.
    pub const INVALID_REQUEST: i64 = -32600;
    /// Unknown method.
    pub const METHOD_NOT_FOUND: i64 = -32601;
    /// Invalid parameters.
    pub const INVALID_PARAMS: i64 = -32602;
    /// Too many requests waiting (server error range).
    pub const BUSY: i64 = -32000;

    /// What a JSON-RPC code means, for people.
    pub fn describe(code: i64) -> Option<&'static str> {
        Some(match code {
            PARSE => "invalid JSON",
            INVALID_REQUEST => "invalid request",
            METHOD_NOT_FOUND => "method not supported",
            INVALID_PARAMS => "invalid parameters",
            BUSY => "gateway busy",
            _ => return None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_listed_code_has_both_languages() {
        for code in ErrorCode::KNOWN {
            let en = code.message("en");
            let de = code.message("DE");
            if code != ErrorCode::GENERAL {
                assert_ne!(en, "General error.", "{code}");
            }
            assert_ne!(en, de, "{code}");
        }
        assert_eq!(ErrorCode(0x0800_0001).message("fr"), "General error.");
        assert_eq!(ErrorCode::NO_OBJECT.to_string(), "06020000h");
    }
}
