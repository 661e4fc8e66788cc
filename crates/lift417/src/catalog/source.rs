//! The catalog's TOML form and its reading: the one place that turns catalog text (the built-in
//! `catalog/lift.toml` at build time, a vendor metadata file at run time) into objects and
//! entries, checked for overlaps between lifts. `build.rs` compiles this module too, so the
//! built-in catalog and a vendor file are read by the same code.

use std::collections::{BTreeMap, BTreeSet};

use canopen::od::ObjectCode;
use canopen::types::DataType;
use nxg::meta::{self, Access, Bound, Description, FormType, Hints, PhysUnit, Privilege, Texts};
use nxg::mplex::Mplex;
use serde::Deserialize;

use crate::lift::{self, MAX_LIFTS};

/// Manufacturer objects marked `per_lift` exist once per lift, lift n at this many indices
/// above lift 1 (our rule: CiA 417 leaves the manufacturer area to us).
pub const MANUFACTURER_LIFT_STRIDE: u16 = 0x100;

/// Why a catalog could not be loaded.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CatalogError {
    /// The TOML is malformed, has an unknown key or a key of the wrong type.
    #[error("line {line}: {reason}")]
    Syntax {
        /// Where (1-based; 0 when unknown).
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// An object or entry is inconsistent.
    #[error("catalog object {index:04X}h: {reason}")]
    Object {
        /// The object (lift 1 index).
        index: u16,
        /// What is wrong.
        reason: String,
    },
}

/// The line of a TOML error: where its span starts, or, for an unknown key (whose span is its
/// table's), the line of that key in the table.
fn error_line(text: &str, span: std::ops::Range<usize>, message: &str) -> usize {
    let start = span.start.min(text.len());
    let first = text[..start].matches('\n').count() + 1;
    let key = message
        .strip_prefix("unknown field `")
        .and_then(|rest| rest.split('`').next());
    let Some(key) = key else {
        return first;
    };
    text[start..]
        .lines()
        .enumerate()
        .take_while(|(i, l)| *i == 0 || !l.trim_start().starts_with('['))
        .map(|(_, l)| l)
        .position(|l| {
            l.trim_start()
                .strip_prefix(key)
                .is_some_and(|rest| rest.trim_start().starts_with('='))
        })
        .map_or(first, |i| first + i)
}

impl CatalogError {
    /// The error as `FILE:LINE: reason`, the line found in `text` (the file's content): the
    /// object's `index = …` line for an inconsistent object.
    pub fn located(&self, file: &str, text: &str) -> String {
        match self {
            CatalogError::Syntax { line, reason } => format!("{file}:{line}: {reason}"),
            CatalogError::Object { index, reason } => {
                let wanted = format!("0x{index:04x}");
                let line = text
                    .lines()
                    .position(|l| {
                        let l = l.trim().to_ascii_lowercase().replace(' ', "");
                        l.starts_with("index=") && l.contains(&wanted)
                    })
                    .map_or(0, |i| i + 1);
                format!("{file}:{line}: object {index:04X}h: {reason}")
            }
        }
    }
}

/// The texts with `{n}` (object number) and `{i}` (sub-index) filled in.
fn expand(texts: &Texts, n: u16, i: u8) -> Texts {
    texts.fill("{n}", n).fill("{i}", i.into())
}

/// The simulated devices a catalog object belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Device {
    /// The lift controller (call controller, drive and door control in one node).
    Controller,
    /// The car/hall I/O node with the call buttons (input panel unit).
    Io,
}

/// One sub-object with its NXg metadata, for lift 1.
#[derive(Debug, Clone, PartialEq)]
pub struct Entry {
    /// Index (lift 1).
    pub index: u16,
    /// Sub-index.
    pub sub: u8,
    /// What `get_canopen_object` reports about it (NXg §6.1.1).
    pub description: Description,
    /// Initial value in CiA text form.
    pub default: Option<String>,
    /// Mappable into PDOs.
    pub pdo: bool,
    /// Kept across restarts (0x1010) although not writable remotely.
    pub persist: bool,
}

impl Entry {
    /// The mplex text of this entry for `index` (`0x` + upper-case hex, docs/PROTOCOL.md
    /// §Mplex).
    pub fn mplex(index: u16, sub: u8) -> String {
        Mplex { index, sub }.to_string()
    }

    /// The CiA 301 type of the values.
    pub fn value_type(&self) -> DataType {
        self.description.datatype.value_type()
    }
}

/// One catalog object (lift 1) as read from the text, before it goes into the tables.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ObjectDef {
    /// Index (lift 1).
    pub index: u16,
    /// Object code.
    pub code: ObjectCode,
    /// Name per language.
    pub name: Texts,
    /// Hint per language.
    pub hint: Texts,
    /// Devices that hold it.
    pub devices: BTreeSet<Device>,
    /// A manufacturer object repeated for every lift.
    pub per_lift: bool,
    /// An array with one element per floor.
    pub per_floor: bool,
    /// Sub-index 0 and the entries that differ from `element`.
    pub listed: BTreeMap<u8, Entry>,
    /// The uniform elements 1..=`last` of an ARRAY, as one entry whose name still holds `{i}`.
    pub element: Option<Entry>,
    /// The highest sub-index.
    pub last: u8,
}

/// A catalog as read from its text: languages, fallbacks and objects by index.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Source {
    /// The languages every text has.
    pub languages: Vec<String>,
    /// Language → the language to use where it has no text.
    pub fallback: BTreeMap<String, String>,
    /// The objects (lift 1), by index.
    pub objects: BTreeMap<u16, ObjectDef>,
}

// ------------------------------------------------------------------------- the TOML form

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawCatalog {
    #[serde(default = "english")]
    languages: Vec<String>,
    #[serde(default)]
    fallback: BTreeMap<String, String>,
    #[serde(default = "count_name")]
    count_name: Texts,
    #[serde(default = "count_hint")]
    count_hint: Texts,
    #[serde(default)]
    object: Vec<RawObject>,
}

/// A file that names no languages is in English.
fn english() -> Vec<String> {
    vec!["en".to_owned()]
}

/// The name of sub-index 0 where a file gives none.
fn count_name() -> Texts {
    Texts::en_de("Number of entries", "Anzahl der Einträge")
}

/// The hint of sub-index 0 where a file gives none.
fn count_hint() -> Texts {
    Texts::en_de(
        "The highest sub-index of this object.",
        "Der höchste Subindex dieses Objekts.",
    )
}

/// Attributes an object passes down to its entries and an entry may override.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawAttrs {
    #[serde(rename = "type")]
    datatype: Option<u32>,
    form: Option<u32>,
    unit: Option<u32>,
    access: Option<String>,
    privilege: Option<u32>,
    min: Option<Bound>,
    max: Option<Bound>,
    zero: Option<bool>,
    list: Option<Vec<Texts>>,
    off_at_zero: Option<bool>,
    unlimited_at_max: Option<bool>,
    undefined_at_max: Option<bool>,
    default: Option<String>,
    pdo: Option<bool>,
    persist: Option<bool>,
}

impl RawAttrs {
    fn or(&self, parent: &RawAttrs) -> RawAttrs {
        RawAttrs {
            datatype: self.datatype.or(parent.datatype),
            form: self.form.or(parent.form),
            unit: self.unit.or(parent.unit),
            access: self.access.clone().or_else(|| parent.access.clone()),
            privilege: self.privilege.or(parent.privilege),
            min: self.min.or(parent.min),
            max: self.max.or(parent.max),
            zero: self.zero.or(parent.zero),
            list: self.list.clone().or_else(|| parent.list.clone()),
            off_at_zero: self.off_at_zero.or(parent.off_at_zero),
            unlimited_at_max: self.unlimited_at_max.or(parent.unlimited_at_max),
            undefined_at_max: self.undefined_at_max.or(parent.undefined_at_max),
            default: self.default.clone().or_else(|| parent.default.clone()),
            pdo: self.pdo.or(parent.pdo),
            persist: self.persist.or(parent.persist),
        }
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawSub {
    sub: u8,
    name: Option<Texts>,
    hint: Option<Texts>,
    #[serde(flatten)]
    attrs: RawAttrs,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RawObject {
    index: u16,
    code: String,
    name: Option<Texts>,
    #[serde(default)]
    hint: Texts,
    repeat: Option<u16>,
    first: Option<u16>,
    #[serde(default)]
    devices: Option<BTreeSet<Device>>,
    #[serde(default)]
    per_lift: bool,
    #[serde(default)]
    per_floor: bool,
    len: Option<u8>,
    item: Option<Texts>,
    #[serde(default)]
    sub: Vec<RawSub>,
    #[serde(flatten)]
    attrs: RawAttrs,
}

pub(crate) fn object_error(index: u16, reason: impl Into<String>) -> CatalogError {
    CatalogError::Object {
        index,
        reason: reason.into(),
    }
}

fn entry_from(
    index: u16,
    sub: u8,
    objcode: ObjectCode,
    name: Texts,
    hint: Texts,
    a: &RawAttrs,
) -> Result<Entry, CatalogError> {
    let err = |e: meta::UnknownCode| object_error(index, format!("sub {sub}: {e}"));
    let code = a
        .datatype
        .ok_or_else(|| object_error(index, format!("sub {sub}: no type")))?;
    let datatype = meta::DataType::from_code(code).map_err(err)?;
    let access = Access::parse(a.access.as_deref().unwrap_or("ro")).map_err(err)?;
    let description = Description {
        objcode: objcode.into(),
        datatype,
        formtype: FormType::from_code(a.form.unwrap_or(0)).map_err(err)?,
        physunit: PhysUnit::from_code(a.unit.unwrap_or(0)).map_err(err)?,
        access,
        privilege: Privilege::from_code(a.privilege.unwrap_or(0)).map_err(err)?,
        name,
        hint,
        min: a.min.or_else(|| type_min(datatype.value_type())),
        max: a.max.or_else(|| type_max(datatype.value_type())),
        zero: a.zero.unwrap_or(false),
        list: a.list.clone().unwrap_or_default(),
        hints: Hints {
            show_off_at_zero: a.off_at_zero.unwrap_or(false),
            show_unlimited_at_max: a.unlimited_at_max.unwrap_or(false),
            show_undefined_at_max: a.undefined_at_max.unwrap_or(false),
        },
    };
    Ok(Entry {
        index,
        sub,
        description,
        default: a.default.clone(),
        pdo: a.pdo.unwrap_or(false),
        persist: a.persist.unwrap_or(false),
    })
}

fn type_min(t: DataType) -> Option<Bound> {
    match t {
        DataType::Real32 => Some(Bound::Real(f64::from(f32::MIN))),
        DataType::Real64 => Some(Bound::Real(f64::MIN)),
        _ => t.integer_range().map(|(lo, _)| Bound::Int(lo)),
    }
}

fn type_max(t: DataType) -> Option<Bound> {
    match t {
        DataType::Real32 => Some(Bound::Real(f64::from(f32::MAX))),
        DataType::Real64 => Some(Bound::Real(f64::MAX)),
        _ => t.integer_range().map(|(_, hi)| Bound::Int(hi)),
    }
}

impl RawObject {
    fn expand(
        &self,
        count_name: &Texts,
        count_hint: &Texts,
    ) -> Result<Vec<ObjectDef>, CatalogError> {
        let code = match self.code.as_str() {
            "var" => ObjectCode::Var,
            "array" => ObjectCode::Array,
            "record" => ObjectCode::Record,
            other => return Err(object_error(self.index, format!("unknown code {other:?}"))),
        };
        let repeat = self.repeat.unwrap_or(1);
        let first = self.first.unwrap_or(1);
        let devices = self
            .devices
            .clone()
            .unwrap_or_else(|| BTreeSet::from([Device::Controller]));
        let mut out = Vec::with_capacity(usize::from(repeat));
        for k in 0..repeat {
            let index = self
                .index
                .checked_add(k)
                .ok_or_else(|| object_error(self.index, "repeat runs past FFFFh"))?;
            let n = first + k;
            let name = expand(
                self.name
                    .as_ref()
                    .ok_or_else(|| object_error(self.index, "no name"))?,
                n,
                0,
            );
            let hint = expand(&self.hint, n, 0);
            let mut entries = BTreeMap::new();
            let mut element = None;
            let mut highest = 0;
            let overrides: BTreeMap<u8, &RawSub> = self.sub.iter().map(|s| (s.sub, s)).collect();
            if overrides.len() != self.sub.len() {
                return Err(object_error(index, "a sub-index is listed twice"));
            }
            match code {
                ObjectCode::Var => {
                    if !self.sub.is_empty() || self.len.is_some() {
                        return Err(object_error(index, "a VAR has no sub list and no len"));
                    }
                    let e = entry_from(index, 0, code, name.clone(), hint.clone(), &self.attrs)?;
                    entries.insert(0, e);
                }
                ObjectCode::Array | ObjectCode::Record => {
                    let subs: Vec<u8> = match (code, self.len) {
                        (ObjectCode::Array, Some(len)) if len > 0 => (1..=len).collect(),
                        (ObjectCode::Array, _) => {
                            return Err(object_error(index, "an ARRAY needs len ≥ 1"))
                        }
                        _ => overrides.keys().copied().collect(),
                    };
                    if let Some(bad) = overrides.keys().find(|s| !subs.contains(s)) {
                        return Err(object_error(index, format!("sub {bad} is outside len")));
                    }
                    let last = *subs
                        .last()
                        .ok_or_else(|| object_error(index, "no entries"))?;
                    // Elements without an override share one template entry.
                    let uniform =
                        |sub: &u8| code == ObjectCode::Array && !overrides.contains_key(sub);
                    if subs.iter().any(uniform) {
                        let template_name = self
                            .item
                            .clone()
                            .ok_or_else(|| object_error(index, "an ARRAY needs item names"))?
                            .fill("{n}", n);
                        element = Some(entry_from(
                            index,
                            1,
                            code,
                            template_name,
                            hint.clone(),
                            &self.attrs,
                        )?);
                    }
                    for &sub in subs.iter().filter(|s| !uniform(s)) {
                        let over = overrides.get(&sub);
                        let attrs = over.map_or(self.attrs.clone(), |o| o.attrs.or(&self.attrs));
                        let sub_name = over
                            .and_then(|o| o.name.clone())
                            .or_else(|| self.item.clone())
                            .ok_or_else(|| object_error(index, format!("sub {sub} has no name")))
                            .map(|t| expand(&t, n, sub))?;
                        let sub_hint = over
                            .and_then(|o| o.hint.clone())
                            .map_or_else(|| hint.clone(), |h| expand(&h, n, sub));
                        let e = entry_from(index, sub, code, sub_name, sub_hint, &attrs)?;
                        entries.insert(sub, e);
                    }
                    let count = RawAttrs {
                        datatype: Some(u32::from(DataType::Unsigned8.code())),
                        form: Some(u32::from(FormType::Number.code())),
                        access: Some("ro".into()),
                        min: Some(Bound::Int(0)),
                        max: Some(Bound::Int(last.into())),
                        default: Some(last.to_string()),
                        ..RawAttrs::default()
                    };
                    let e = entry_from(
                        index,
                        0,
                        code,
                        count_name.clone(),
                        count_hint.clone(),
                        &count,
                    )?;
                    entries.insert(0, e);
                    highest = last;
                }
                _ => return Err(object_error(index, "only var, array and record")),
            }
            out.push(ObjectDef {
                index,
                code,
                name,
                hint,
                devices: devices.clone(),
                per_lift: self.per_lift,
                per_floor: self.per_floor,
                listed: entries,
                element,
                last: highest,
            });
        }
        Ok(out)
    }
}

/// Where the object at lift-1 index `index` lives for `lift`, if it exists for that lift.
pub(crate) fn index_for_lift(index: u16, per_lift: bool, lift: u8) -> Option<u16> {
    if lift == 1 {
        return Some(index);
    }
    if lift::lift_of(index).is_some() {
        return lift::for_lift(index, lift);
    }
    if per_lift && (1..=MAX_LIFTS).contains(&lift) {
        return index.checked_add(u16::from(lift - 1) * MANUFACTURER_LIFT_STRIDE);
    }
    None
}

impl Source {
    /// Read a catalog from its TOML text; objects must not overlap for any lift.
    pub fn parse(text: &str) -> Result<Source, CatalogError> {
        let raw: RawCatalog = toml::from_str(text).map_err(|e| CatalogError::Syntax {
            line: e
                .span()
                .map_or(0, |span| error_line(text, span, e.message())),
            reason: e.message().to_owned(),
        })?;
        let mut objects = BTreeMap::new();
        for o in &raw.object {
            for object in o.expand(&raw.count_name, &raw.count_hint)? {
                let index = object.index;
                if objects.insert(index, object).is_some() {
                    return Err(object_error(index, "defined twice"));
                }
            }
        }
        let source = Source {
            languages: raw.languages,
            fallback: raw.fallback,
            objects,
        };
        source.check_lift_collisions()?;
        Ok(source)
    }

    fn check_lift_collisions(&self) -> Result<(), CatalogError> {
        let mut taken: BTreeMap<u16, (u16, u8)> = BTreeMap::new();
        for o in self.objects.values() {
            for lift in 1..=MAX_LIFTS {
                let Some(index) = index_for_lift(o.index, o.per_lift, lift) else {
                    continue;
                };
                if let Some((other, other_lift)) = taken.insert(index, (o.index, lift)) {
                    return Err(object_error(
                        o.index,
                        format!(
                            "lift {lift} lands on {index:04X}h, already taken by \
                             {other:04X}h of lift {other_lift}"
                        ),
                    ));
                }
            }
        }
        Ok(())
    }
}
