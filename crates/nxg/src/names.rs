//! Objects by name: the index an operator's words are resolved with (docs/PROTOCOL.md §Mplex,
//! "Addresses people type"). Names come from whoever describes the objects — the CiA 417
//! catalog, an EDS — in any number of languages; the lookup is case-insensitive, an exact name
//! wins, otherwise a unique prefix is enough. The portal resolves `?name=` with it, the command
//! line tools their object words; the wire only ever carries the mplex.

use crate::mplex::{BadMplex, Mplex};

/// One nameable object.
#[derive(Debug, Clone)]
struct Named {
    /// The name as shown.
    name: String,
    /// The name lower-cased, as compared.
    key: String,
    mplex: Mplex,
}

/// Names of objects (several per object: one per language, or an object's and its sub's).
#[derive(Debug, Clone, Default)]
pub struct ObjectNames(Vec<Named>);

/// Why words do not name one object.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NameError {
    /// Neither an address nor a known name.
    #[error("{0:?} is neither an object address (0x652001, 0x6520:1) nor the name of an object")]
    Unknown(String),
    /// More than one object starts with the words: the candidates, by address.
    #[error("{text:?} names {} objects: {}", candidates.len(), list(candidates))]
    Ambiguous {
        /// The words as given.
        text: String,
        /// Each object's name and address, in address order.
        candidates: Vec<(String, Mplex)>,
    },
    /// Looked like an address (a digit or `0x` first) but is none.
    #[error(transparent)]
    Address(#[from] BadMplex),
}

/// The first eight candidates, `…` for more.
fn list(candidates: &[(String, Mplex)]) -> String {
    let shown: Vec<String> = candidates
        .iter()
        .take(8)
        .map(|(name, mplex)| format!("{name} ({mplex})"))
        .collect();
    let more = if candidates.len() > 8 { ", …" } else { "" };
    format!("{}{more}", shown.join(", "))
}

impl ObjectNames {
    /// An empty index: only addresses resolve.
    pub fn new() -> Self {
        ObjectNames::default()
    }

    /// Add a name of `mplex`.
    pub fn push(&mut self, name: impl Into<String>, mplex: Mplex) {
        let name = name.into();
        let key = name.trim().to_lowercase();
        if !key.is_empty() {
            self.0.push(Named { name, key, mplex });
        }
    }

    /// How many names are known.
    pub fn len(&self) -> usize {
        self.0.len()
    }

    /// Whether no name is known.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }

    /// The first name given for `mplex` (the catalog gives English first).
    pub fn name_of(&self, mplex: Mplex) -> Option<&str> {
        self.0
            .iter()
            .find(|n| n.mplex == mplex)
            .map(|n| n.name.as_str())
    }

    /// The object named `text`: an exact name (any case), or the only object whose name starts
    /// with it.
    pub fn by_name(&self, text: &str) -> Result<Mplex, NameError> {
        let wanted = text.trim().to_lowercase();
        let hits = |exact: bool| {
            let mut hits: Vec<&Named> = self
                .0
                .iter()
                .filter(|n| {
                    if exact {
                        n.key == wanted
                    } else {
                        n.key.starts_with(&wanted)
                    }
                })
                .collect();
            hits.sort_by_key(|n| n.mplex);
            hits.dedup_by_key(|n| n.mplex);
            hits
        };
        let exact = hits(true);
        let found = if exact.is_empty() { hits(false) } else { exact };
        match found.as_slice() {
            _ if wanted.is_empty() => Err(NameError::Unknown(text.to_owned())),
            [one] => Ok(one.mplex),
            [] => Err(NameError::Unknown(text.chars().take(64).collect())),
            many => Err(NameError::Ambiguous {
                text: text.to_owned(),
                candidates: many.iter().map(|n| (n.name.clone(), n.mplex)).collect(),
            }),
        }
    }

    /// One word as operators type it: an address ([`Mplex::parse_address`]) when it starts
    /// like a number (a digit or `0x`, so `add` or `bad` are names, not hex), else a name.
    pub fn resolve(&self, text: &str) -> Result<Mplex, NameError> {
        if looks_numeric(text) {
            Ok(Mplex::parse_address(text)?)
        } else {
            self.by_name(text)
        }
    }
}

/// Whether the text is meant as a number.
pub fn looks_numeric(text: &str) -> bool {
    let t = text.trim();
    t.starts_with("0x")
        || t.starts_with("0X")
        || t.bytes().next().is_some_and(|b| b.is_ascii_digit())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn m(index: u16, sub: u8) -> Mplex {
        Mplex { index, sub }
    }

    fn sample() -> ObjectNames {
        let mut names = ObjectNames::new();
        names.push("Trip counter", m(0x6520, 1));
        names.push("Fahrtenzähler", m(0x6520, 1));
        names.push("Car position", m(0x6383, 1));
        names.push("Car speed", m(0x6384, 1));
        names.push("Car", m(0x6000, 0));
        names
    }

    #[test]
    fn names_addresses_and_ambiguity() {
        let names = sample();
        for text in [
            "Trip counter",
            "TRIP COUNTER",
            " trip ",
            "fahrtenZ",
            "0x652001",
            "0x6520:1",
            "6520sub1",
        ] {
            assert_eq!(names.resolve(text), Ok(m(0x6520, 1)), "{text}");
        }
        // An exact name wins over the prefix it is of the others.
        assert_eq!(names.resolve("car"), Ok(m(0x6000, 0)));
        assert_eq!(names.resolve(" Car "), Ok(m(0x6000, 0)));
    }

    #[test]
    fn failures_say_why() {
        let names = sample();
        assert_eq!(names.resolve("car p"), Ok(m(0x6383, 1)), "a unique prefix");
        assert_eq!(names.resolve("car s"), Ok(m(0x6384, 1)));
        let e = names.by_name("ca").unwrap_err();
        let NameError::Ambiguous { candidates, .. } = &e else {
            panic!("{e:?}");
        };
        assert_eq!(candidates.len(), 3);
        assert_eq!(candidates[0].1, m(0x6000, 0), "address order");
        assert!(e.to_string().contains("Car position (0x638301)"), "{e}");
        assert!(matches!(names.resolve("door"), Err(NameError::Unknown(_))));
        assert!(matches!(names.resolve(""), Err(NameError::Unknown(_))));
        assert_eq!(names.resolve("0x65"), Ok(m(0x65, 0)), "an index alone");
        assert!(matches!(names.resolve("0xZZ"), Err(NameError::Address(_))));
        assert!(matches!(
            ObjectNames::new().resolve("trip"),
            Err(NameError::Unknown(_))
        ));
        assert_eq!(names.name_of(m(0x6520, 1)), Some("Trip counter"));
    }
}
