//! Where the gateway's session learns what objects are: the built-in CiA 417 catalog for the
//! lift controller, EDS/DCF files for other nodes (names, data types, access and limits as the
//! file gives them; writing needs setup rights), nothing for nodes without one (requests then
//! bring their `datatype`, NXg §6.5).

use std::collections::HashMap;

use canopen::od::ObjectDictionary;
use canopen::types::{DataType, Value};
use lift417::catalog::Catalog;
use nxg::gateway::{bare, Lookup, Metadata, Target};
use nxg::meta::{Access, Bound, FormType, Texts};

/// Metadata for a bus.
#[derive(Default)]
pub struct BusMetadata {
    /// The lift controller (described by the catalog).
    pub controller: Option<Target>,
    /// Dictionaries imported from EDS files, by node.
    pub nodes: HashMap<Target, ObjectDictionary>,
}

fn bound(v: &Value) -> Option<Bound> {
    match v {
        Value::Int(i) => Some(Bound::Int((*i).into())),
        Value::Uint(u) => Some(Bound::Int((*u).into())),
        Value::Real32(r) => Some(Bound::Real((*r).into())),
        Value::Real64(r) => Some(Bound::Real(*r)),
        _ => None,
    }
}

impl Metadata for BusMetadata {
    fn lookup(&self, target: Target, index: u16, sub: u8) -> Lookup {
        if Some(target) == self.controller {
            return Catalog::builtin().describe(index, sub);
        }
        let Some(od) = self.nodes.get(&target) else {
            return Lookup::Unknown;
        };
        let Some(object) = od.object(index) else {
            return Lookup::NoObject;
        };
        let Some(var) = object.subs.get(&sub) else {
            return Lookup::NoSub;
        };
        let mut d = bare(var.data_type.into());
        d.objcode = object.code.into();
        d.access = Access::from(var.access);
        d.name = Texts::english(&var.name);
        d.formtype = match var.data_type {
            DataType::VisibleString | DataType::UnicodeString => FormType::Text,
            DataType::OctetString | DataType::Domain => FormType::Hex,
            DataType::Real32 | DataType::Real64 => FormType::Real,
            _ => FormType::Number,
        };
        if let Some(low) = var.low.as_ref().and_then(bound) {
            d.min = Some(low);
        }
        if let Some(high) = var.high.as_ref().and_then(bound) {
            d.max = Some(high);
        }
        if let Some(len) = var.max_len {
            d.max = Some(Bound::Int(len as i128));
        }
        Lookup::Found(Box::new(d))
    }

    fn object_texts(&self, target: Target, index: u16) -> Option<(Texts, Texts)> {
        if Some(target) == self.controller {
            return Catalog::builtin().object_texts(index);
        }
        let object = self.nodes.get(&target)?.object(index)?;
        Some((Texts::english(&object.name), Texts::default()))
    }

    fn text<'a>(
        &'a self,
        texts: &'a Texts,
        preferred: &str,
        alternate: &str,
    ) -> Option<(&'a str, &'a str)> {
        Catalog::builtin().text(texts, preferred, alternate)
    }
}
