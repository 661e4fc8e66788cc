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
