//! Where a session learns what an object is: the [`Metadata`] trait, which the gateway daemon
//! implements from the CiA 417 catalog, EDS/DCF files and vendor descriptions.

use crate::meta::{Access, Bound, DataType, Description, FormType, Hints, ObjCode, PhysUnit};
use crate::meta::{Privilege, Texts};

/// Which node and network a request is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Target {
    /// CAN network (1 = the gateway's own bus).
    pub net: u8,
    /// Node-ID.
    pub node: u8,
}

/// What a metadata source knows of a sub-object.
#[derive(Debug, Clone, PartialEq)]
pub enum Lookup {
    /// Its description.
    Found(Box<Description>),
    /// The object exists, the sub-index does not.
    NoSub,
    /// The object does not exist.
    NoObject,
    /// Nothing is known of this node: the request's `datatype` must do.
    Unknown,
}

/// Where metadata comes from.
pub trait Metadata: Send + Sync {
    /// The description of (`index`, `sub`) on `target`.
    fn lookup(&self, target: Target, index: u16, sub: u8) -> Lookup;

    /// The name and hint of the whole object, for a `compact` read of an array (NXg §6.2).
    fn object_texts(&self, _target: Target, _index: u16) -> Option<(Texts, Texts)> {
        None
    }

    /// `texts` in the caller's language: `preferred`, then `alternate`, then English;
    /// (language, text). A source with language fallbacks of its own overrides this.
    fn text<'a>(
        &'a self,
        texts: &'a Texts,
        preferred: &str,
        alternate: &str,
    ) -> Option<(&'a str, &'a str)> {
        texts.first_of([preferred, alternate, "en"])
    }
}

/// The description of a sub-object of a node the gateway knows nothing about: the caller's
/// data type (NXg §6.5), writable, and only with setup rights.
pub fn bare(datatype: DataType) -> Description {
    let (min, max) = match datatype.value_type().integer_range() {
        Some((lo, hi)) => (Some(Bound::Int(lo)), Some(Bound::Int(hi))),
        None => (None, None),
    };
    Description {
        objcode: ObjCode::Var,
        datatype,
        formtype: FormType::Raw,
        physunit: PhysUnit::None,
        access: Access::Rw,
        privilege: Privilege::Setup,
        name: Texts::default(),
        hint: Texts::default(),
        min,
        max,
        zero: false,
        list: Vec::new(),
        hints: Hints::default(),
    }
}
