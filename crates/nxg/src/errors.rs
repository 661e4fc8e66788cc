//! Errors of the connector: CiA 301 abort codes as JSON numbers (NXg SW003 §8.6, DESIGN.md §4)
//! with a message in the caller's language, and the JSON-RPC codes of invalid messages.

use canopen::sdo::abort::AbortCode;

/// An NXg error: the abort code, and what `data` carries (the mplex, or the privilege).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct NxgError {
    /// The CiA 301 abort code.
    pub code: AbortCode,
    /// `data`: usually the mplex as the caller wrote it.
    pub data: String,
    /// A more precise English message than the code's (e.g. the lock-out time), if any.
    pub detail: Option<String>,
}

impl NxgError {
    /// An error about `data`.
    pub fn new(code: AbortCode, data: impl Into<String>) -> Self {
        NxgError {
            code,
            data: data.into(),
            detail: None,
        }
    }
}

/// Privilege too low, or "engineer on site" (DESIGN.md §4).
pub const PRIVILEGE: AbortCode = AbortCode(0x0800_0021);
/// Wrong serial number or password hash (DESIGN.md §4).
pub const IDENTITY: AbortCode = AbortCode(0x0800_0020);
/// Data type or physical unit do not match.
pub const TYPE_MISMATCH: AbortCode = AbortCode(0x0607_0010);
/// String too long.
pub const TOO_LONG: AbortCode = AbortCode(0x0607_0012);

/// The message for `code` in `lang` (English and German; other languages get English).
pub fn message(code: AbortCode, lang: &str) -> &'static str {
    let german = lang.eq_ignore_ascii_case("de");
    let (en, de) = match code.0 {
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
        0x0800_0024 => ("No data available.", "Keine Daten verfügbar."),
        _ => ("General error.", "Allgemeiner Fehler."),
    };
    if german {
        de
    } else {
        en
    }
}

/// JSON-RPC 2.0 error codes for messages that are not valid requests (DESIGN.md §4).
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
}

/// An error object of a gateway's answer (`{"code", "message", "data"}`) as an operator reads it:
/// `message (CODEh, data)`, the abort code in the hex form of CiA 301.
pub fn describe(error: &serde_json::Value) -> String {
    let code = match &error["code"] {
        serde_json::Value::Null => String::new(),
        code => code
            .as_i64()
            .map_or_else(|| code.to_string(), |c| format!("{c:08X}h")),
    };
    let data = match &error["data"] {
        serde_json::Value::Null => String::new(),
        data => format!(", {data}"),
    };
    let message = error["message"].as_str().unwrap_or("error");
    format!("{message} ({code}{data})")
}

#[cfg(test)]
mod tests {
    #[test]
    fn describes_an_error_object() {
        let e = serde_json::json!({"code": 0x0602_0000, "message": "Object does not exist in the object dictionary.", "data": "0x5FFF00"});
        assert_eq!(
            super::describe(&e),
            "Object does not exist in the object dictionary. (06020000h, \"0x5FFF00\")"
        );
        assert_eq!(
            super::describe(&serde_json::json!({"code": 1, "message": "m"})),
            "m (00000001h)"
        );
    }

    use super::*;

    #[test]
    fn every_listed_code_has_both_languages() {
        for code in [
            0u32,
            0x0503_0000,
            0x0504_0000,
            0x0504_0001,
            0x0504_0005,
            0x0601_0000,
            0x0601_0001,
            0x0601_0002,
            0x0602_0000,
            0x0604_0043,
            0x0607_0010,
            0x0607_0012,
            0x0607_0013,
            0x0609_0011,
            0x0609_0030,
            0x0609_0031,
            0x0609_0032,
            0x0609_0036,
            0x0800_0020,
            0x0800_0021,
            0x0800_0024,
        ] {
            let en = message(AbortCode(code), "en");
            let de = message(AbortCode(code), "DE");
            assert_ne!(en, "General error.", "{code:08X}");
            assert_ne!(en, de, "{code:08X}");
        }
        assert_eq!(message(AbortCode(0x0800_0000), "fr"), "General error.");
    }
}
