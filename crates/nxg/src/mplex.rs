//! The object multiplexer of the connector: `"0x"` and six hex digits, index then sub-index
//! (NXg SW003 §6.1; docs/PROTOCOL.md §Mplex: case-insensitive on input, upper-case when the
//! gateway writes).

use std::fmt;

/// An object address: index and sub-index.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Mplex {
    /// Index.
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
}

/// Why a text is not an mplex.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{0:?} is not an mplex (0x and six hex digits: index, sub-index)")]
pub struct BadMplex(pub String);

impl Mplex {
    /// Parse `0x652001` (any case of `x` and of the digits).
    pub fn parse(text: &str) -> Result<Mplex, BadMplex> {
        let bad = || BadMplex(text.chars().take(32).collect());
        let digits = text
            .strip_prefix("0x")
            .or_else(|| text.strip_prefix("0X"))
            .filter(|d| d.len() == 6 && d.bytes().all(|b| b.is_ascii_hexdigit()))
            .ok_or_else(bad)?;
        let value = u32::from_str_radix(digits, 16).map_err(|_| bad())?;
        Ok(Mplex {
            index: (value >> 8) as u16,
            sub: value as u8,
        })
    }
}

impl Mplex {
    /// Parse an object address as operators type it: the mplex (`0x652001`, `652001`), index
    /// and sub-index (`0x6520:1`, `6520:1`, `0x6520sub1`, `6520sub1`; the index in hex with or
    /// without `0x`, the sub-index in decimal or `0x` hex), or an index alone (`0x6520`: sub 0).
    /// The wire keeps the strict [`Mplex::parse`] (docs/PROTOCOL.md §Mplex).
    pub fn parse_address(text: &str) -> Result<Mplex, BadMplex> {
        let bad = || BadMplex(text.chars().take(32).collect());
        let t = text.trim();
        let hex = |d: &str| {
            let d = d
                .strip_prefix("0x")
                .or_else(|| d.strip_prefix("0X"))
                .unwrap_or(d);
            (!d.is_empty() && d.len() <= 4 && d.bytes().all(|b| b.is_ascii_hexdigit()))
                .then(|| u16::from_str_radix(d, 16).ok())
                .flatten()
        };
        let sub = |d: &str| match d.strip_prefix("0x").or_else(|| d.strip_prefix("0X")) {
            Some(h) if !h.is_empty() && h.len() <= 2 => u8::from_str_radix(h, 16).ok(),
            Some(_) => None,
            None if !d.is_empty() && d.bytes().all(|b| b.is_ascii_digit()) => d.parse().ok(),
            None => None,
        };
        let lower = t.to_ascii_lowercase();
        if let Some((i, s)) = lower.split_once(':').or_else(|| lower.split_once("sub")) {
            return Ok(Mplex {
                index: hex(i).ok_or_else(bad)?,
                sub: sub(s).ok_or_else(bad)?,
            });
        }
        let digits = lower.strip_prefix("0x").unwrap_or(&lower);
        match digits.len() {
            6 => Mplex::parse(&format!("0x{digits}")).map_err(|_| bad()),
            1..=4 => Ok(Mplex {
                index: hex(digits).ok_or_else(bad)?,
                sub: 0,
            }),
            _ => Err(bad()),
        }
    }
}

/// An mplex in the gateway's spelling (`0x` + upper-case hex), or the text as it came if it is
/// none: the portal's key for stored values and the web page's key for live ones.
pub fn normalized(text: &str) -> String {
    Mplex::parse(text).map_or_else(|_| text.to_owned(), |m| m.to_string())
}

impl fmt::Display for Mplex {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "0x{:04X}{:02X}", self.index, self.sub)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn parses_the_specification_samples() {
        assert_eq!(
            Mplex::parse("0x652001"),
            Ok(Mplex {
                index: 0x6520,
                sub: 1
            })
        );
        assert_eq!(Mplex::parse("0X63b0ff").unwrap().to_string(), "0x63B0FF");
        for bad in [
            "652001",
            "0x65201",
            "0x6520011",
            "0x65200g",
            "",
            "0x",
            "0x+65200",
        ] {
            assert!(Mplex::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn addresses_as_operators_type_them() {
        let m = |index, sub| Ok(Mplex { index, sub });
        for (text, want) in [
            ("0x652001", m(0x6520, 1)),
            ("652001", m(0x6520, 1)),
            ("0x6520:1", m(0x6520, 1)),
            ("6520:1", m(0x6520, 1)),
            ("0x6520sub1", m(0x6520, 1)),
            ("6520SUB1", m(0x6520, 1)),
            ("0x6520:0x0A", m(0x6520, 10)),
            (" 0x1017 ", m(0x1017, 0)),
            ("1017", m(0x1017, 0)),
        ] {
            assert_eq!(Mplex::parse_address(text), want, "{text}");
        }
        for bad in [
            "",
            "0x",
            "0x6520:",
            ":1",
            "0x65200:1",
            "6520:256",
            "0x6520:1:2",
            "door",
            "0x1234567",
        ] {
            assert!(Mplex::parse_address(bad).is_err(), "{bad}");
        }
    }

    proptest! {
        #[test]
        fn round_trips(index: u16, sub: u8) {
            let m = Mplex { index, sub };
            prop_assert_eq!(Mplex::parse(&m.to_string()), Ok(m));
            prop_assert_eq!(Mplex::parse(&m.to_string().to_lowercase()), Ok(m));
        }

        #[test]
        fn never_panics(text in ".{0,12}") {
            let _ = Mplex::parse(&text);
        }
    }
}
