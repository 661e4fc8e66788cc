//! Object addresses as people type them, for `canlift sdo`, `get`, `put` and `watch`: an mplex
//! (`0x652001`), index and sub-index (`0x6520:1`, `6520sub1`, or two words `0x6520 1`), or an
//! object's name from the CiA 417 catalog or an EDS (`"Trip counter"`: case-insensitive, English
//! or German, a unique prefix is enough). The data type comes with a name, and for numeric
//! addresses from the same sources when they describe the object.

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{bail, Context};
use canopen::types::{self, DataType};
use lift417::catalog::Catalog;
use nxg::mplex::Mplex;
use nxg::names::ObjectNames;

/// Where names and types come from: an EDS, or the catalog.
pub struct Names {
    names: ObjectNames,
    types: BTreeMap<Mplex, DataType>,
}

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
        let catalog = Catalog::builtin();
        let types = catalog
            .objects()
            .flat_map(|object| {
                object.entries().map(move |entry| {
                    let mplex = Mplex {
                        index: object.index(),
                        sub: entry.sub,
                    };
                    (mplex, entry.value_type())
                })
            })
            .collect();
        Names {
            names: catalog.names(),
            types,
        }
    }

    /// The objects an EDS or DCF describes (`Object / Sub` for the sub-objects of a record
    /// or array, and the sub-object's own name).
    pub fn eds(path: &Path) -> anyhow::Result<Self> {
        let description = canopen::eds::import_file(path, None)?.logged();
        let mut names = ObjectNames::new();
        let mut types = BTreeMap::new();
        for object in description.od.objects() {
            for (&sub, var) in &object.subs {
                let mplex = Mplex {
                    index: object.index,
                    sub,
                };
                types.insert(mplex, var.data_type);
                if object.subs.len() == 1 {
                    names.push(object.name.clone(), mplex);
                } else {
                    names.push(format!("{} / {}", object.name, var.name), mplex);
                    names.push(var.name.clone(), mplex);
                }
            }
        }
        Ok(Names { names, types })
    }

    /// The EDS given, else the catalog.
    pub fn eds_or_catalog(eds: Option<&Path>) -> anyhow::Result<Self> {
        match eds {
            Some(path) => Names::eds(path),
            None => Ok(Names::catalog()),
        }
    }

    /// The name of (index, sub): English first for the catalog, `Object / Sub` for the
    /// sub-objects of an EDS's records and arrays.
    pub fn name_of(&self, index: u16, sub: u8) -> Option<&str> {
        self.names.name_of(Mplex { index, sub })
    }

    fn resolved(&self, mplex: Mplex) -> Resolved {
        Resolved {
            mplex,
            data_type: self.types.get(&mplex).copied(),
        }
    }

    /// Resolve one word: an address form, else a name.
    pub fn resolve(&self, text: &str) -> anyhow::Result<Resolved> {
        Ok(self.resolved(self.names.resolve(text)?))
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
            return Ok((self.resolved(mplex), words.get(2).map(String::as_str)));
        }
        if words.len() > 2 {
            bail!("too many words after the node: {words:?} (quote a name with spaces)");
        }
        Ok((self.resolve(first)?, words.get(1).map(String::as_str)))
    }
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
