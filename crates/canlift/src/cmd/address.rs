//! Object addresses as people type them, for `canlift sdo`, `get`, `put` and `watch`: an mplex
//! (`0x652001`), index and sub-index (`0x6520:1`, `6520sub1`, or two words `0x6520 1`), or an
//! object's name from the CiA 417 catalog or an EDS (`"Trip counter"`: case-insensitive, English
//! or German, a unique prefix is enough). The data type comes with a name, and for numeric
//! addresses from the same sources when they describe the object.

use std::path::Path;

use anyhow::{bail, Context};
use canopen::types::{self, DataType};
use lift417::catalog::Catalog;
use nxg::mplex::Mplex;

/// One nameable object.
struct Named {
    /// The name as shown.
    name: String,
    index: u16,
    sub: u8,
    data_type: DataType,
}

/// Where names and types come from: an EDS, or the catalog.
pub struct Names(Vec<Named>);

/// An address resolved.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Resolved {
    /// Index and sub-index.
    pub mplex: Mplex,
    /// Its data type, when the source describes it.
    pub data_type: Option<DataType>,
}

impl Names {
    /// The objects of the CiA 417 catalog (lift 1), with their English and German names.
    pub fn catalog() -> Self {
        let mut named = Vec::new();
        for object in Catalog::builtin().objects() {
            for entry in object.entries() {
                for lang in ["en", "de"] {
                    if let Some(name) = entry.description.name.get(lang) {
                        named.push(Named {
                            name: name.to_owned(),
                            index: object.index,
                            sub: entry.sub,
                            data_type: entry.value_type(),
                        });
                    }
                }
            }
        }
        Names(named)
    }

    /// The objects an EDS or DCF describes (`Object / Sub` for the sub-objects of a record
    /// or array, and the sub-object's own name).
    pub fn eds(path: &Path) -> anyhow::Result<Self> {
        let description = canopen::eds::import_file(path, None)?;
        let mut named = Vec::new();
        for object in description.od.objects() {
            for (&sub, var) in &object.subs {
                let mut add = |name: String| {
                    named.push(Named {
                        name,
                        index: object.index,
                        sub,
                        data_type: var.data_type,
                    })
                };
                if object.subs.len() == 1 {
                    add(object.name.clone());
                } else {
                    add(format!("{} / {}", object.name, var.name));
                    add(var.name.clone());
                }
            }
        }
        Ok(Names(named))
    }

    /// The EDS given, else the catalog.
    pub fn eds_or_catalog(eds: Option<&Path>) -> anyhow::Result<Self> {
        match eds {
            Some(path) => Names::eds(path),
            None => Ok(Names::catalog()),
        }
    }

    fn named(&self, mplex: Mplex) -> Option<&Named> {
        self.0
            .iter()
            .find(|n| n.index == mplex.index && n.sub == mplex.sub)
    }

    fn data_type(&self, mplex: Mplex) -> Option<DataType> {
        self.named(mplex).map(|n| n.data_type)
    }

    /// The name of (index, sub): English first for the catalog, `Object / Sub` for the
    /// sub-objects of an EDS's records and arrays.
    pub fn name_of(&self, index: u16, sub: u8) -> Option<&str> {
        self.named(Mplex { index, sub }).map(|n| n.name.as_str())
    }

    /// The object named `text`: an exact name, or the only object whose name starts with it.
    fn by_name(&self, text: &str) -> anyhow::Result<Resolved> {
        let wanted = text.trim().to_lowercase();
        let found = |exact: bool| {
            let mut hits: Vec<&Named> = self
                .0
                .iter()
                .filter(|n| {
                    let name = n.name.to_lowercase();
                    if exact {
                        name == wanted
                    } else {
                        name.starts_with(&wanted)
                    }
                })
                .collect();
            hits.sort_by_key(|n| (n.index, n.sub));
            hits.dedup_by_key(|n| (n.index, n.sub));
            hits
        };
        let exact = found(true);
        let hits = if exact.is_empty() {
            found(false)
        } else {
            exact
        };
        match hits.as_slice() {
            [one] => Ok(Resolved {
                mplex: Mplex {
                    index: one.index,
                    sub: one.sub,
                },
                data_type: Some(one.data_type),
            }),
            [] => bail!("{text:?} is neither an object address (0x652001, 0x6520:1) nor the name of an object"),
            many => {
                let list: Vec<String> = many
                    .iter()
                    .take(8)
                    .map(|n| format!("{} ({})", n.name, Mplex { index: n.index, sub: n.sub }))
                    .collect();
                bail!(
                    "{text:?} names {} objects: {}{}",
                    many.len(),
                    list.join(", "),
                    if many.len() > 8 { ", …" } else { "" }
                )
            }
        }
    }

    /// Resolve one word: an address form, else a name.
    pub fn resolve(&self, text: &str) -> anyhow::Result<Resolved> {
        match Mplex::parse_address(text) {
            Ok(mplex) if looks_numeric(text) => Ok(Resolved {
                mplex,
                data_type: self.data_type(mplex),
            }),
            _ => self.by_name(text),
        }
    }

    /// Resolve the words after the node: `INDEX SUB [TYPE]` (the classic form) or
    /// `ADDRESS [TYPE]`. Returns the address and the TYPE word, if any.
    pub fn resolve_words<'a>(
        &self,
        words: &'a [String],
    ) -> anyhow::Result<(Resolved, Option<&'a str>)> {
        let Some(first) = words.first() else {
            bail!("give the object: INDEX SUB, 0x6520:1, 0x652001 or a name");
        };
        let as_number = |w: &str| types::parse_integer(w);
        if let (Some(index), Some(sub)) =
            (as_number(first), words.get(1).and_then(|w| as_number(w)))
        {
            let mplex = Mplex {
                index: u16::try_from(index).context("the index is above 0xFFFF")?,
                sub: u8::try_from(sub).context("the sub-index is above 255")?,
            };
            if words.len() > 3 {
                bail!("too many words after the node: {words:?}");
            }
            let resolved = Resolved {
                mplex,
                data_type: self.data_type(mplex),
            };
            return Ok((resolved, words.get(2).map(String::as_str)));
        }
        if words.len() > 2 {
            bail!("too many words after the node: {words:?} (quote a name with spaces)");
        }
        Ok((self.resolve(first)?, words.get(1).map(String::as_str)))
    }
}

/// Whether the text is meant as a number (so `add` or `bad` are names, not hex).
fn looks_numeric(text: &str) -> bool {
    let t = text.trim().to_ascii_lowercase();
    t.starts_with("0x") || t.bytes().next().is_some_and(|b| b.is_ascii_digit())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn words(w: &[&str]) -> Vec<String> {
        w.iter().map(|s| (*s).to_owned()).collect()
    }

    #[test]
    fn addresses_and_names() {
        let names = Names::catalog();
        let trip = Mplex {
            index: 0x6520,
            sub: 1,
        };
        for text in [
            "0x652001",
            "0x6520:1",
            "6520sub1",
            "trip counter",
            "TRIP COUNTER",
            "Fahrtenz",
        ] {
            let r = names
                .resolve(text)
                .unwrap_or_else(|e| panic!("{text}: {e}"));
            assert_eq!(r.mplex, trip, "{text}");
            assert_eq!(r.data_type, Some(DataType::Unsigned32), "{text}");
        }
        let classic = words(&["0x1017", "0", "u16"]);
        let (r, ty) = names.resolve_words(&classic).unwrap();
        assert_eq!((r.mplex.index, r.mplex.sub, ty), (0x1017, 0, Some("u16")));
        let address = words(&["0x6520:1", "x32"]);
        let (r, ty) = names.resolve_words(&address).unwrap();
        assert_eq!((r.mplex, ty), (trip, Some("x32")));
        let name = words(&["Trip counter"]);
        let (r, ty) = names.resolve_words(&name).unwrap();
        assert_eq!((r.mplex, ty), (trip, None));
        let e = names.resolve("car").unwrap_err().to_string();
        assert!(e.contains("names") && e.contains("objects"), "{e}");
        assert!(names.resolve("no such thing").is_err());
        assert!(names
            .resolve_words(&words(&["0x1017", "0", "u16", "x"]))
            .is_err());
    }
}
