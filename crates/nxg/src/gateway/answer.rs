//! Building the gateway's answers: a `get_canopen_object` answer in its forms (NXg SW003
//! §6.1.1–§6.2.2) from a description and the bytes read, a `put_canopen_object` value checked
//! against its description (§6.3), and error objects in the caller's language.

use std::borrow::Cow;

use canopen::types::{self, Value as CoValue};

use super::metadata::Metadata;
use crate::codes::ErrorCode;
use crate::meta::{Access, Bound, Description, Privilege};
use crate::msg::{AnswerLang, ErrorObject, Lang, ObjectAnswer, ObjectData};

/// Longest language tag kept from a request.
const MAX_LANG: usize = 16;

/// The caller's languages, as a session keeps them: English costs no allocation, a request's
/// own tags are its strings, cut to length.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Langs {
    pub(crate) preferred: Cow<'static, str>,
    pub(crate) alternate: Cow<'static, str>,
}

impl Default for Langs {
    fn default() -> Self {
        Langs {
            preferred: Cow::Borrowed("en"),
            alternate: Cow::Borrowed("en"),
        }
    }
}

impl Langs {
    /// The languages of a request's `lang` (alternate defaults to preferred).
    pub(crate) fn of(lang: Lang) -> Option<Langs> {
        let short = |mut l: String| -> Cow<'static, str> {
            if let Some((end, _)) = l.char_indices().nth(MAX_LANG) {
                l.truncate(end);
            }
            Cow::Owned(l)
        };
        let preferred = short(lang.preferred_language?);
        let alternate = lang
            .alternate_language
            .map_or_else(|| preferred.clone(), short);
        Some(Langs {
            preferred,
            alternate,
        })
    }
}

/// How much a `get_canopen_object` answer carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Form {
    Full,
    Stripped,
    Naked,
}

/// Why a request is refused with an NXg error: the abort code, what `data` carries (usually
/// the mplex as the caller wrote it) and, optionally, a more precise English message than the
/// code's (the lock-out time, for instance).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct Refusal {
    pub(crate) code: ErrorCode,
    pub(crate) data: String,
    pub(crate) detail: Option<String>,
}

impl Refusal {
    pub(crate) fn new(code: impl Into<ErrorCode>, data: impl Into<String>) -> Refusal {
        Refusal {
            code: code.into(),
            data: data.into(),
            detail: None,
        }
    }

    pub(crate) fn detailed(
        code: ErrorCode,
        data: impl Into<String>,
        detail: impl Into<String>,
    ) -> Refusal {
        Refusal {
            code,
            data: data.into(),
            detail: Some(detail.into()),
        }
    }

    /// The error object in `lang` (details are English; German gets the code's message).
    pub(crate) fn to_error(&self, lang: &Langs) -> ErrorObject {
        let message = match (&self.detail, lang.preferred.eq_ignore_ascii_case("de")) {
            (Some(detail), false) => detail.clone(),
            _ => self.code.message(&lang.preferred).to_owned(),
        };
        ErrorObject::new(self.code, message, Some(&self.data))
    }
}

fn bound(b: Option<Bound>) -> Option<serde_json::Number> {
    b.and_then(Bound::to_json)
}

/// The answer to a read of `mplex` described by `d`, whose value bytes are `values` (one
/// element, or every element of a `compact` read).
pub(crate) fn object(
    metadata: &dyn Metadata,
    d: &Description,
    form: Form,
    lang: &Langs,
    mplex: &str,
    values: &[Vec<u8>],
) -> Result<ObjectAnswer, ErrorCode> {
    let ty = d.datatype.value_type();
    let value = values
        .iter()
        .map(|bytes| {
            types::decode(ty, bytes)
                .map(|v| types::to_text(ty, &v))
                .map_err(|_| ErrorCode::TYPE_MISMATCH)
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut object = ObjectData {
        mplex: mplex.to_owned(),
        value,
        ..ObjectData::default()
    };
    if form == Form::Naked {
        return Ok(ObjectAnswer {
            object,
            ..ObjectAnswer::default()
        });
    }
    object.objcode = Some(d.objcode.code());
    object.datatype = Some(u32::from(d.datatype.code()));
    object.formtype = Some(u32::from(d.formtype.code()));
    object.physunit = Some(u32::from(d.physunit.code()));
    // NXg §8.4 names privileges 0–2: an object only an engineer on site may write is, to a
    // peer of the connector, one it cannot write — read-only, at the highest privilege the
    // spec names (docs/PROTOCOL.md §Privileges).
    let (access, privilege) = match (d.privilege, d.access) {
        (Privilege::EngineerOnSite, Access::Rw) => (Access::Ro, Privilege::Setup),
        (Privilege::EngineerOnSite, access) => (access, Privilege::Setup),
        (privilege, access) => (access, privilege),
    };
    object.access = Some(access.text().to_owned());
    object.privilege = Some(u32::from(privilege.code()));
    object.min = bound(d.min);
    object.max = bound(d.max);
    // NXg §6.1.1: a string's `max` is its maximum count of characters — for one that cannot be
    // written, the characters it holds (a writable one without a stated limit has none known).
    let string = matches!(
        ty,
        canopen::types::DataType::VisibleString | canopen::types::DataType::UnicodeString
    );
    if object.max.is_none() && string && !access.writable() {
        object.max = object
            .value
            .iter()
            .map(|v| v.chars().count())
            .max()
            .map(serde_json::Number::from);
    }
    object.zero = Some(d.zero);
    if form == Form::Stripped {
        return Ok(ObjectAnswer {
            object,
            ..ObjectAnswer::default()
        });
    }
    let name = metadata.text(&d.name, &lang.preferred, &lang.alternate);
    let hint = metadata.text(&d.hint, &lang.preferred, &lang.alternate);
    let used = name.map_or("en", |n| n.0);
    object.name = Some(name.map_or("", |n| n.1).to_owned());
    object.hint = Some(hint.map_or("", |h| h.1).to_owned());
    object.list = Some(
        d.list
            .iter()
            .map(|t| {
                metadata
                    .text(t, used, &lang.alternate)
                    .map_or("", |x| x.1)
                    .to_owned()
            })
            .collect(),
    );
    Ok(ObjectAnswer {
        lang: Some(AnswerLang {
            language: used.to_owned(),
        }),
        object,
        hints: Some(d.hints),
    })
}

/// The bytes to write for the text `value` of an object described by `d`: the text form of
/// docs/PROTOCOL.md §Values, within the data type's range (too high/too low otherwise) and the
/// description's limits (0 allowed where `zero` says so; strings up to `max` characters).
pub(crate) fn value_to_write(d: &Description, value: &str) -> Result<Vec<u8>, ErrorCode> {
    let ty = d.datatype.value_type();
    let parsed = types::from_text(ty, value).map_err(|e| ErrorCode::from(e.abort_code()))?;
    check_range(d, &parsed)?;
    types::encode(ty, &parsed).map_err(|_| ErrorCode::INVALID_VALUE)
}

fn check_range(d: &Description, value: &CoValue) -> Result<(), ErrorCode> {
    if let CoValue::Text(t) = value {
        if let Some(Bound::Int(max)) = d.max {
            if t.chars().count() as i128 > max {
                return Err(ErrorCode::TOO_LONG);
            }
        }
        return Ok(());
    }
    let Some(v) = value.as_f64() else {
        return Ok(());
    };
    if d.zero && v == 0.0 {
        return Ok(());
    }
    if d.min.is_some_and(|m| v < m.as_f64()) {
        return Err(ErrorCode::TOO_LOW);
    }
    if d.max.is_some_and(|m| v > m.as_f64()) {
        return Err(ErrorCode::TOO_HIGH);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gateway::metadata::bare;
    use crate::meta::DataType;

    #[test]
    fn a_requests_languages_are_cut_to_length_and_default_to_each_other() {
        let long = "dé-ÄÖÜ-0123456789-suffix";
        let langs = Langs::of(Lang {
            preferred_language: Some(long.into()),
            alternate_language: None,
        })
        .expect("a preferred language");
        assert_eq!(langs.preferred, "dé-ÄÖÜ-012345678");
        assert_eq!(langs.alternate, langs.preferred);
        let langs = Langs::of(Lang::new("de", "fr")).expect("a preferred language");
        assert_eq!((&*langs.preferred, &*langs.alternate), ("de", "fr"));
        assert_eq!(Langs::of(Lang::default()), None);
    }

    #[test]
    fn values_are_checked_against_type_and_limits() {
        let mut d = bare(DataType::UNSIGNED8);
        assert_eq!(value_to_write(&d, "010"), Ok(vec![10]));
        assert_eq!(value_to_write(&d, "0x10"), Ok(vec![16]));
        assert_eq!(value_to_write(&d, "256"), Err(ErrorCode::TOO_HIGH));
        assert_eq!(value_to_write(&d, "-1"), Err(ErrorCode::TOO_LOW));
        assert_eq!(value_to_write(&d, "four"), Err(ErrorCode::INVALID_VALUE));
        d.min = Some(Bound::Int(10));
        d.max = Some(Bound::Int(99));
        assert_eq!(value_to_write(&d, "5"), Err(ErrorCode::TOO_LOW));
        assert_eq!(value_to_write(&d, "0"), Err(ErrorCode::TOO_LOW));
        d.zero = true;
        assert_eq!(value_to_write(&d, "0"), Ok(vec![0]));
        let mut s = bare(DataType::VISIBLE_STRING);
        s.max = Some(Bound::Int(3));
        assert_eq!(value_to_write(&s, "abcd"), Err(ErrorCode::TOO_LONG));
        assert_eq!(value_to_write(&s, "abc"), Ok(b"abc".to_vec()));
    }

    #[test]
    fn refusals_speak_the_callers_language() {
        let r = Refusal::detailed(
            ErrorCode::IDENTITY,
            "1",
            "The password hash does not match.",
        );
        let en = r.to_error(&Langs::default());
        assert_eq!(en.message, "The password hash does not match.");
        let de = r.to_error(&Langs {
            preferred: "de".into(),
            alternate: "en".into(),
        });
        assert_eq!(de.message, ErrorCode::IDENTITY.message("de"));
        assert_eq!(de.data_text().as_deref(), Some("1"));
    }
}
