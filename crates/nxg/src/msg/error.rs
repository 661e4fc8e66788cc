//! The error object of an answer (JSON-RPC 2.0 §5.1 as NXg SW003 §5.4.3, §6.3.3, §7.1.3 use
//! it): a CiA 301 abort code or a JSON-RPC code, a message in the caller's language, and the
//! object (or privilege) it concerns.

use serde::{Deserialize, Deserializer, Serialize};

use crate::codes::{rpc_codes, ErrorCode};

/// `{"code", "message", "data"}`. `code` is written as a number; read as a number or as a
/// string in decimal or `0x` hex, since the specification shows both (docs/PROTOCOL.md
/// §Errors).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ErrorObject {
    /// A CiA 301 abort code (positive) or a JSON-RPC code (negative).
    #[serde(deserialize_with = "lenient_code")]
    pub code: i64,
    /// What went wrong, in the caller's language.
    #[serde(default)]
    pub message: String,
    /// The mplex as the caller wrote it, the privilege asked for, or anything else; may be
    /// omitted.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub data: Option<serde_json::Value>,
}

fn lenient_code<'de, D: Deserializer<'de>>(d: D) -> Result<i64, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Code {
        Number(i64),
        Text(String),
    }
    Ok(match Code::deserialize(d)? {
        Code::Number(n) => n,
        Code::Text(t) => parse_code(&t).unwrap_or(i64::from(ErrorCode::GENERAL.0)),
    })
}

fn parse_code(text: &str) -> Option<i64> {
    let t = text.trim();
    match t.strip_prefix("0x").or_else(|| t.strip_prefix("0X")) {
        Some(hex) => i64::from_str_radix(hex, 16).ok(),
        None => t.parse().ok(),
    }
}

impl ErrorObject {
    /// An NXg error: `code` with `message`, about `data` (the mplex, usually).
    pub fn new(code: ErrorCode, message: String, data: Option<&str>) -> ErrorObject {
        ErrorObject {
            code: i64::from(code.0),
            message,
            data: data.map(|d| serde_json::Value::String(d.to_owned())),
        }
    }

    /// A JSON-RPC error (a negative `code`), without data.
    pub fn rpc(code: i64, message: impl Into<String>) -> ErrorObject {
        ErrorObject {
            code,
            message: message.into(),
            data: None,
        }
    }

    /// Read an error object leniently: a member of the wrong type leaves a general error with
    /// the text kept as its message, rather than losing the answer.
    pub fn read(text: &str) -> ErrorObject {
        serde_json::from_str(text).unwrap_or_else(|_| ErrorObject {
            code: i64::from(ErrorCode::GENERAL.0),
            message: text.chars().take(200).collect(),
            data: None,
        })
    }

    /// The CiA 301 abort code, when `code` is one.
    pub fn abort_code(&self) -> Option<ErrorCode> {
        u32::try_from(self.code).ok().map(ErrorCode)
    }

    /// `data` as text (a string as it is, anything else as JSON).
    pub fn data_text(&self) -> Option<String> {
        self.data.as_ref().map(|d| match d {
            serde_json::Value::String(s) => s.clone(),
            other => other.to_string(),
        })
    }
}

impl std::fmt::Display for ErrorObject {
    /// As an operator reads it: `message (06020000h, 0x5FFF00)`, abort codes in the hex form of
    /// CiA 301, JSON-RPC codes by name.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let message = if self.message.is_empty() {
            "error"
        } else {
            &self.message
        };
        write!(f, "{message} (")?;
        match (self.abort_code(), rpc_codes::describe(self.code)) {
            (Some(code), _) => write!(f, "{code}")?,
            (None, Some(name)) => write!(f, "{name}")?,
            (None, None) => write!(f, "code {}", self.code)?,
        }
        if let Some(data) = self.data_text() {
            write!(f, ", {data}")?;
        }
        write!(f, ")")
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn codes_are_read_in_every_form_the_specification_shows() {
        for text in [
            r#"{"code":134217761,"message":"m"}"#,
            r#"{"code":"134217761","message":"m"}"#,
            r#"{"code":"0x08000021","message":"m"}"#,
            r#"{"code":"0X08000021","message":"m"}"#,
        ] {
            assert_eq!(ErrorObject::read(text).code, 0x0800_0021, "{text}");
        }
        let odd = ErrorObject::read(r#"{"code":"<CANOPEN ABORT CODE>","message":"m"}"#);
        assert_eq!(odd.abort_code(), Some(ErrorCode::GENERAL));
        let broken = ErrorObject::read(r#"{"code":[1]}"#);
        assert_eq!(broken.abort_code(), Some(ErrorCode::GENERAL));
    }

    #[test]
    fn describes_itself_for_operators() {
        let e = ErrorObject::new(
            ErrorCode::NO_OBJECT,
            "Object does not exist in the object dictionary.".into(),
            Some("0x5FFF00"),
        );
        assert_eq!(
            e.to_string(),
            "Object does not exist in the object dictionary. (06020000h, 0x5FFF00)"
        );
        assert_eq!(
            ErrorObject::rpc(rpc_codes::INVALID_PARAMS, "object.mplex: bad").to_string(),
            "object.mplex: bad (invalid parameters)"
        );
        assert_eq!(
            ErrorObject {
                code: 1,
                message: "m".into(),
                data: None
            }
            .to_string(),
            "m (00000001h)"
        );
        assert_eq!(ErrorObject::rpc(-5, "").to_string(), "error (code -5)");
    }
}
