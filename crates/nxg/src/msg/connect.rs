//! The messages that set a connection up and keep it trusted: CONNECT and its answer (NXg
//! SW003 §5.2), the cloud token (§5.4) and privilege elevation (§6.4).

use serde::{Deserialize, Serialize};
use serde_json::value::RawValue;

/// Longest text field of CONNECT the portal accepts.
pub const MAX_FIELD: usize = 256;
/// Longest cloud token (NXg SW003 §5.4).
pub const MAX_TOKEN: usize = 128;

/// The `identity` of CONNECT (NXg SW003 §5.2.1).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Identity {
    /// Serial number (unique per vendor).
    pub sernum: String,
    /// CiA vendor-ID.
    pub vendorid: u32,
    /// Product code.
    pub productcode: u32,
    /// Lift number as the owner knows it.
    #[serde(default)]
    pub liftnum: String,
    /// Hardware description.
    #[serde(default)]
    pub hardware: String,
    /// Software version.
    #[serde(default)]
    pub software: String,
    /// Highest API version the gateway offers; absent means 1 (NXg §5.2.1).
    #[serde(default = "api_one")]
    pub api: u32,
    /// Hash identifying the board.
    #[serde(default)]
    pub boardhash: String,
    /// The token the portal gave the gateway earlier; absent before the first one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cloudtoken: Option<String>,
}

fn api_one() -> u32 {
    1
}

/// CONNECT's parameters (NXg SW003 §5.2.1).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Connect {
    /// Who the gateway is.
    pub identity: Identity,
    /// Which account it belongs to.
    #[serde(default)]
    pub domaintoken: String,
}

impl Connect {
    /// What the portal checks beyond the types: the serial number is there, texts are bounded,
    /// free of control, format and private-use characters and in Unicode's composed normal
    /// form (NFC), the API version is at least 1, the token at most 128 characters
    /// (docs/PROTOCOL.md §Connection).
    ///
    /// Control characters have no place in an identity, and one of them (NUL) is a text
    /// PostgreSQL refuses to store: the portal asks about many CONNECTs in one statement, so one
    /// gateway's NUL would fail the admissions of the others asked with it. Format characters
    /// (a zero-width space, a direction mark), private-use ones and texts in another normal
    /// form look like another identity on a screen while being a different one: a second
    /// lift beside the real one that an operator cannot tell apart.
    pub fn validate(&self) -> Result<(), String> {
        let id = &self.identity;
        if id.sernum.is_empty() {
            return Err("identity.sernum must not be empty".into());
        }
        let token = id.cloudtoken.as_deref().unwrap_or_default();
        for (name, text, longest) in [
            ("sernum", id.sernum.as_str(), MAX_FIELD),
            ("liftnum", &id.liftnum, MAX_FIELD),
            ("hardware", &id.hardware, MAX_FIELD),
            ("software", &id.software, MAX_FIELD),
            ("boardhash", &id.boardhash, MAX_FIELD),
            ("domaintoken", &self.domaintoken, MAX_FIELD),
            ("identity.cloudtoken", token, MAX_TOKEN),
        ] {
            if text.chars().count() > longest {
                return Err(format!("{name} is longer than {longest} characters"));
            }
            if let Some(why) = unfit(text) {
                return Err(format!("{name} holds {why}"));
            }
        }
        if id.api == 0 {
            return Err("identity.api must be ≥ 1".into());
        }
        Ok(())
    }
}

/// What makes `text` unfit for an identity, if anything: a control, format or private-use
/// character (named by its code point), or a form other than NFC.
fn unfit(text: &str) -> Option<String> {
    use unicode_properties::{GeneralCategory, UnicodeGeneralCategory};
    for c in text.chars() {
        let kind = match c.general_category() {
            GeneralCategory::Control => "a control character",
            GeneralCategory::Format => "a format character",
            GeneralCategory::PrivateUse => "a private-use character",
            GeneralCategory::Surrogate | GeneralCategory::Unassigned => "an unassigned code point",
            _ => continue,
        };
        return Some(format!("{kind} (U+{:04X})", u32::from(c)));
    }
    if !unicode_normalization::is_nfc(text) {
        return Some("text not in Unicode normal form C (NFC)".into());
    }
    None
}

/// The portal's answer to CONNECT: the API version in force.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Connack {
    /// The portal's API version (the gateway takes the smaller of it and its own).
    pub api: u32,
}

impl Connack {
    /// Read a CONNECT answer: `"result": "CONNACK"` with `api` beside it, as the sample (NXg
    /// §5.2.2), or `"result": {"connack": …, "api": N}`; no `api` means 1 (docs/PROTOCOL.md
    /// §Connection).
    pub fn read(result: &RawValue, api: Option<&RawValue>) -> Result<Connack, String> {
        #[derive(Deserialize)]
        #[serde(untagged)]
        enum Form {
            Word(String),
            Object {
                #[serde(alias = "CONNACK", rename = "connack")]
                _connack: serde::de::IgnoredAny,
                api: Option<u64>,
            },
        }
        let number = |raw: Option<&RawValue>| raw.and_then(|a| a.get().parse::<u64>().ok());
        let api = match serde_json::from_str::<Form>(result.get()) {
            Ok(Form::Word(w)) if w.eq_ignore_ascii_case("CONNACK") => number(api),
            Ok(Form::Object { api: inner, .. }) => inner.or(number(api)),
            _ => return Err(format!("unexpected CONNECT answer: {}", result.get())),
        };
        let api = api.unwrap_or(1).clamp(1, u64::from(u32::MAX)) as u32;
        Ok(Connack { api })
    }
}

/// `update_unique_token` (NXg SW003 §5.4.1).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct TokenParams {
    /// The gateway's serial number, as a check.
    pub sernum: String,
    /// The token to store (at most 128 characters).
    pub token: String,
}

/// `elevate_privilege` (NXg SW003 §6.4.1).
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ElevateParams {
    /// The gateway's serial number, as a check.
    pub sernum: String,
    /// The privilege asked for (1 service, 2 setup).
    pub privilege: u32,
    /// Unsalted SHA-1 hex of the password (any case).
    pub passhash: String,
}

/// The answer to `elevate_privilege` (NXg SW003 §6.4.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
pub struct ElevateAnswer {
    /// Seconds the privilege lasts.
    pub duration: u64,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn connack(result: &str, api: Option<&str>) -> Result<u32, String> {
        let result: Box<RawValue> = serde_json::from_str(result).unwrap();
        let api: Option<Box<RawValue>> = api.map(|a| serde_json::from_str(a).unwrap());
        Connack::read(&result, api.as_deref()).map(|c| c.api)
    }

    #[test]
    fn connack_forms() {
        assert_eq!(connack(r#""CONNACK""#, Some("2")), Ok(2));
        assert_eq!(connack(r#""connack""#, None), Ok(1));
        assert_eq!(connack(r#"{"connack":true,"api":5}"#, None), Ok(5));
        assert_eq!(connack(r#"{"CONNACK":1}"#, Some("3")), Ok(3));
        assert!(connack(r#""NACK""#, None).is_err());
        assert!(connack(r#"{"api":2}"#, None).is_err());
    }

    #[test]
    fn connect_sample_and_validation() {
        let sample = r#"{"identity":{"sernum":"180917010200000102","vendorid":1050,"productcode":4096,
            "liftnum":"40/7289/20399-126","hardware":"Thor @ NX-T2","software":"01.23.10","api":1,
            "boardhash":"2354A687AF6DC79B203E754E8E426A87FE188A62983B7AC48F9D5E195B728112",
            "cloudtoken":"2A98765DE230176C"},"domaintoken":"MAS"}"#;
        let c: Connect = serde_json::from_str(sample).unwrap();
        assert_eq!(c.identity.cloudtoken.as_deref(), Some("2A98765DE230176C"));
        assert_eq!(c.validate(), Ok(()));
        let bare: Connect =
            serde_json::from_str(r#"{"identity":{"sernum":"1","vendorid":1,"productcode":2}}"#)
                .unwrap();
        assert_eq!((bare.identity.api, bare.domaintoken.as_str()), (1, ""));
        let mut bad = bare.clone();
        bad.identity.sernum.clear();
        assert!(bad.validate().is_err());
        let mut bad = bare.clone();
        bad.identity.cloudtoken = Some("x".repeat(129));
        assert!(bad.validate().unwrap_err().contains("cloudtoken"));
        let mut bad = bare.clone();
        bad.identity.sernum = "18091701\u{0}".into();
        assert_eq!(
            bad.validate(),
            Err("sernum holds a control character (U+0000)".into())
        );
        // Look-alikes: a zero-width space, a direction mark, a private-use character, a
        // decomposed umlaut beside the composed one.
        for (text, why) in [
            ("1809170102\u{200b}", "a format character (U+200B)"),
            ("\u{202e}2010", "a format character (U+202E)"),
            ("18\u{e000}", "a private-use character (U+E000)"),
            ("Mu\u{308}ller", "not in Unicode normal form C"),
        ] {
            let mut bad = bare.clone();
            bad.identity.sernum = text.into();
            let refused = bad.validate().unwrap_err();
            assert!(refused.contains(why), "{text:?}: {refused}");
        }
        let mut fine = bare.clone();
        fine.identity.sernum = "M\u{fc}ller-2024/17 #3".into();
        fine.identity.hardware = "Thor @ NX-T2 · Ω".into();
        assert_eq!(fine.validate(), Ok(()));
        let mut bad = bare.clone();
        bad.domaintoken = "MAS\n".into();
        assert!(bad.validate().unwrap_err().contains("domaintoken"));
        let mut bad = bare;
        bad.identity.cloudtoken = Some("2A98\u{7f}".into());
        assert!(bad.validate().unwrap_err().contains("cloudtoken"));
    }
}
