//! Where the gateway's session learns what objects are (docs/GATEWAY.md §Metadata):
//!
//! - which objects a node has, their data type, access, limits and default come from its EDS or
//!   DCF (`[[bus.nodes]] eds`);
//! - the NXg metadata — names and hints per language, form, unit, privilege, lists, `zero`,
//!   presentation hints — from the vendor's metadata file (`metadata`, in the catalog's own
//!   format), else from the CiA 417 catalog or the CiA 301 communication profile when they
//!   describe the index with the same data type, else derived from the EDS (its ParameterName,
//!   a form from the data type, no unit, the policy's default privilege);
//! - a node without an EDS: the lift controller is described by its vendor file, the CiA 417
//!   catalog and the communication profile (objects that turn out missing answer as the node
//!   does); another node by its vendor file if it has one, else not at all (reads bring their
//!   `datatype`, writes are refused).
//!
//! A defect of an EDS or DCF is logged as a warning naming `FILE:LINE` and only the defective
//! part is left out (canopen::eds); an EDS without any usable object, or a malformed metadata
//! file, stops the gateway at start with `FILE:LINE: reason`.

mod cia301;

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use canopen::od::ObjectDictionary;
use canopen::types::{DataType as CiaType, Value};
use lift417::catalog::{Catalog, Device};
use nxg::gateway::{bare, Lookup, Metadata, Target};
use nxg::meta::{Access, Bound, Description, FormType, Privilege, Texts};

use crate::config::{Config, NodeSection};
use crate::GatewayError;

/// The manufacturer-specific profile area (CiA 301 §7.4.1).
const MANUFACTURER: std::ops::RangeInclusive<u16> = 0x2000..=0x5FFF;

/// Whether the catalog's object named `catalog` is the EDS's object named `eds`: in the
/// manufacturer-specific area, where the same index means something else on every vendor's
/// device, only when the English names agree (an EDS exported by `canlift sim`); elsewhere the
/// index says it.
fn same_object(index: u16, catalog: &Texts, eds_name: &str) -> bool {
    !MANUFACTURER.contains(&index)
        || catalog
            .get("en")
            .is_some_and(|a| a.trim().eq_ignore_ascii_case(eds_name.trim()))
}

/// What describes one node.
#[derive(Default)]
pub struct NodeMetadata {
    /// The dictionary of its EDS or DCF (shared: an embedded gateway's is its controller's,
    /// and many gateways in one process may describe the same controller).
    eds: Option<Arc<ObjectDictionary>>,
    /// The vendor's metadata (catalog format).
    vendor: Option<Catalog>,
    /// Whether the EDS says it is a CiA 417 device (1000h names profile 417): only then does
    /// the lift catalog describe its objects — a CiA 401 I/O module's 6000h is not a lift's.
    /// Read once, when the EDS is.
    lift_profile: bool,
}

impl NodeMetadata {
    fn new(eds: Option<Arc<ObjectDictionary>>, vendor: Option<Catalog>) -> NodeMetadata {
        let lift_profile = eds.as_ref().is_some_and(|od| {
            matches!(od.get_value(0x1000, 0), Ok(Value::Uint(v)) if v & 0xFFFF == u64::from(PROFILE_417))
        });
        NodeMetadata {
            eds,
            vendor,
            lift_profile,
        }
    }
}

/// CiA 301 device profile number of CiA 417 (1000h bits 0–15).
const PROFILE_417: u16 = 417;

/// Metadata for the gateway's networks.
pub struct BusMetadata {
    /// The lift controller.
    pub controller: Target,
    /// What writing needs where no metadata says.
    pub default_privilege: Privilege,
    /// Nodes with an EDS or vendor metadata.
    pub nodes: HashMap<Target, NodeMetadata>,
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

/// How a value of `ty` is shown when nothing says otherwise.
fn form_of(ty: CiaType) -> FormType {
    match ty {
        CiaType::VisibleString | CiaType::UnicodeString => FormType::Text,
        CiaType::OctetString | CiaType::Domain => FormType::Hex,
        CiaType::Real32 | CiaType::Real64 => FormType::Real,
        CiaType::Boolean => FormType::Switch,
        _ => FormType::Number,
    }
}

/// The first description the sources give; else "no sub-index" if one of them knows the object.
fn first_of(lookups: impl IntoIterator<Item = Lookup>) -> Lookup {
    let mut knows_object = false;
    for l in lookups {
        match l {
            Lookup::Found(d) => return Lookup::Found(d),
            Lookup::NoSub => knows_object = true,
            Lookup::NoObject | Lookup::Unknown => {}
        }
    }
    if knows_object {
        Lookup::NoSub
    } else {
        Lookup::NoObject
    }
}

/// The communication profile's answer as a lookup.
fn standard(index: u16, sub: u8) -> Lookup {
    match cia301::describe(index, sub) {
        Some(Some(d)) => Lookup::Found(Box::new(d)),
        Some(None) => Lookup::NoSub,
        None => Lookup::NoObject,
    }
}

impl BusMetadata {
    /// Read the EDS and metadata files `config` names.
    pub fn load(config: &Config) -> Result<BusMetadata, GatewayError> {
        let mut nodes = HashMap::new();
        for (net, list) in config.node_sections() {
            for n in list {
                nodes.insert(Target { net, node: n.id }, load_node(n)?);
            }
        }
        Ok(BusMetadata {
            controller: Target {
                net: 1,
                node: config.bus.lift_controller,
            },
            default_privilege: config.policy.default_privilege(),
            nodes,
        })
    }

    /// `od` describes `target` (which objects exist, types, access, limits) unless an EDS
    /// was configured for it: the dictionary of the controller an embedded gateway serves.
    pub fn with_dictionary(mut self, target: Target, od: Arc<ObjectDictionary>) -> BusMetadata {
        let node = self.nodes.entry(target).or_default();
        if node.eds.is_none() {
            *node = NodeMetadata::new(Some(od), node.vendor.take());
        }
        self
    }

    /// Whether the lift catalog describes `target`: the lift controller, or a CiA 417 device.
    fn is_lift(&self, target: Target) -> bool {
        target == self.controller || self.nodes.get(&target).is_some_and(|n| n.lift_profile)
    }

    /// The NXg part of a description from the vendor file, the catalog or the communication
    /// profile, when one describes (`index`, `sub`) with the data type of `d` (the EDS's).
    /// The catalog describes only a lift (`lift`: the lift controller, or a CiA 417 device);
    /// in the manufacturer-specific area (2000h–5FFFh), where the same index means something
    /// else on every vendor's device, its texts apply only to an object the EDS names as the
    /// catalog does (an EDS exported by `canlift sim`).
    fn nxg_part(
        &self,
        vendor: Option<&Catalog>,
        lift: bool,
        (index, sub): (u16, u8),
        d: &Description,
        eds_name: &str,
    ) -> Option<Description> {
        let same_type = |l: Lookup| match l {
            Lookup::Found(found) if found.datatype == d.datatype => Some(*found),
            _ => None,
        };
        vendor
            .and_then(|v| same_type(v.describe(None, index, sub)))
            .or_else(|| {
                same_type(Catalog::builtin().describe(None, index, sub))
                    .filter(|c| lift && same_object(index, &c.name, eds_name))
            })
            .or_else(|| same_type(standard(index, sub)))
    }

    /// A node with an EDS: the merge rule.
    fn merged(
        &self,
        od: &ObjectDictionary,
        vendor: Option<&Catalog>,
        lift: bool,
        index: u16,
        sub: u8,
    ) -> Lookup {
        let Some(object) = od.object(index) else {
            return Lookup::NoObject;
        };
        let Some(var) = object.subs.get(&sub) else {
            return Lookup::NoSub;
        };
        let mut d = bare(var.data_type.into());
        d.objcode = object.code.into();
        d.access = Access::from(var.access);
        d.formtype = form_of(var.data_type);
        d.privilege = self.default_privilege;
        if let Some(low) = var.low.as_ref().and_then(bound) {
            d.min = Some(low);
        }
        if let Some(high) = var.high.as_ref().and_then(bound) {
            d.max = Some(high);
        }
        if let Some(len) = var.max_len {
            d.max = Some(Bound::Int(len as i128));
        }
        if let Some(n) = self.nxg_part(vendor, lift, (index, sub), &d, &var.name) {
            d.name = n.name.or_english(&var.name);
            d.hint = n.hint;
            d.formtype = n.formtype;
            d.physunit = n.physunit;
            d.privilege = n.privilege;
            d.list = n.list;
            d.zero = n.zero;
            d.hints = n.hints;
        } else {
            d.name = Texts::english(&var.name);
        }
        Lookup::Found(Box::new(d))
    }
}

impl Metadata for BusMetadata {
    fn lookup(&self, target: Target, index: u16, sub: u8) -> Lookup {
        let node = self.nodes.get(&target);
        let vendor = node.and_then(|n| n.vendor.as_ref());
        let controller = target == self.controller;
        if let Some(od) = node.and_then(|n| n.eds.as_ref()) {
            return self.merged(od, vendor, self.is_lift(target), index, sub);
        }
        if vendor.is_none() && !controller {
            return Lookup::Unknown;
        }
        let communication = (0x1000..=0x1FFF).contains(&index);
        first_of(
            [
                vendor.map(|v| v.describe(None, index, sub)),
                controller
                    .then(|| Catalog::builtin().describe(Some(Device::Controller), index, sub)),
                communication.then(|| standard(index, sub)),
            ]
            .into_iter()
            .flatten(),
        )
    }

    fn object_texts(&self, target: Target, index: u16) -> Option<(Texts, Texts)> {
        let node = self.nodes.get(&target);
        let vendor = node.and_then(|n| n.vendor.as_ref());
        let from_vendor = || vendor.and_then(|v| v.object_texts(None, index));
        let Some(od) = node.and_then(|n| n.eds.as_ref()) else {
            let controller = target == self.controller;
            if vendor.is_none() && !controller {
                return None;
            }
            let catalog = || {
                controller
                    .then(|| Catalog::builtin().object_texts(Some(Device::Controller), index))
                    .flatten()
            };
            return from_vendor()
                .or_else(catalog)
                .or_else(|| cia301::object_texts(index));
        };
        let object = od.object(index)?;
        let eds = Texts::english(&object.name);
        let lift = self.is_lift(target);
        let catalog = || {
            Catalog::builtin()
                .object_texts(None, index)
                .filter(|(name, _)| lift && same_object(index, name, &object.name))
        };
        Some(
            match from_vendor()
                .or_else(catalog)
                .or_else(|| cia301::object_texts(index))
            {
                Some((name, hint)) => (eds.overlay(&name), hint),
                None => (eds, Texts::default()),
            },
        )
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

/// Read a node's EDS and vendor metadata; the vendor's data types must agree with the EDS.
fn load_node(n: &NodeSection) -> Result<NodeMetadata, GatewayError> {
    let eds = match &n.eds {
        Some(path) => Some(Arc::new(
            canopen::eds::import_file(path, Some(n.id))?.logged().od,
        )),
        None => None,
    };
    let vendor = match &n.metadata {
        Some(path) => Some(load_vendor(path, eds.as_deref())?),
        None => None,
    };
    Ok(NodeMetadata::new(eds, vendor))
}

/// A vendor metadata file: the catalog's format; every object it describes that the EDS has
/// must have the EDS's data type.
fn load_vendor(path: &Path, eds: Option<&ObjectDictionary>) -> Result<Catalog, GatewayError> {
    let file = path.display().to_string();
    let text = std::fs::read_to_string(path)
        .map_err(|e| GatewayError::Metadata(format!("{file}: {e}")))?;
    let catalog =
        Catalog::from_toml(&text).map_err(|e| GatewayError::Metadata(e.located(&file, &text)))?;
    let Some(od) = eds else {
        return Ok(catalog);
    };
    for object in catalog.objects() {
        for entry in object.entries() {
            let Some(var) = od
                .object(object.index())
                .and_then(|o| o.subs.get(&entry.sub))
            else {
                tracing::warn!(
                    file,
                    index = object.index(),
                    sub = entry.sub,
                    "described by the vendor file, absent from the EDS: answers 06020000h"
                );
                continue;
            };
            if entry.description.datatype != var.data_type.into() {
                let located = lift417::catalog::CatalogError::Object {
                    index: object.index(),
                    reason: format!(
                        "sub {}: data type {:#04X} in the vendor file, {} in the EDS",
                        entry.sub,
                        entry.description.datatype.code(),
                        var.data_type
                    ),
                };
                return Err(GatewayError::Metadata(located.located(&file, &text)));
            }
        }
    }
    Ok(catalog)
}

#[cfg(test)]
mod tests;
