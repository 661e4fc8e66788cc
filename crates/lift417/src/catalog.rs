//! The object catalog: every object a canlift lift controller (and its I/O node) holds, with the
//! metadata `get_canopen_object` reports (NXg SW003 §6.1): object code, data type, form, unit,
//! access, privilege, names and hints per language, limits, lists and presentation hints.
//!
//! The data lives in `catalog/lift.toml`, compiled into the binary; [`Catalog::builtin`] parses
//! it once. Objects are described for lift 1. The lift-number rule of CiA 417-4 §4.1.1 (lift n at
//! +(n − 1) × 800h, see [`crate::lift`]) and ours for manufacturer objects marked `per_lift`
//! (lift n at +(n − 1) × [`MANUFACTURER_LIFT_STRIDE`]) are applied here, by code:
//! [`Catalog::lookup`] answers for any lift, [`Catalog::dictionary`] builds a device's object
//! dictionary for any number of lifts.

use std::borrow::Cow;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::{Arc, OnceLock};

use canopen::od::{self, Object, ObjectCode, ObjectDictionary, Variable, VariableHook};
use canopen::sdo::abort::AbortCode;
use canopen::types::{self, DataType, Value};
use nxg::gateway::Lookup;
use nxg::meta::{self, Access, Bound, Description, FormType, Hints, PhysUnit, Privilege, Texts};
use nxg::mplex::Mplex;
use nxg::names::ObjectNames;
use serde::Deserialize;

use crate::lift::{self, MAX_LIFTS};

/// The catalog source compiled into canlift.
pub const BUILTIN_TOML: &str = include_str!("../catalog/lift.toml");

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

/// One catalog object (lift 1) with its entries; arrays and records have a generated sub 0.
#[derive(Debug, Clone, PartialEq)]
pub struct CatalogObject {
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
    /// An array with one element per floor (the device sizes it by its number of floors).
    pub per_floor: bool,
    /// Sub-index 0 and the entries that differ from `element`.
    listed: BTreeMap<u8, Entry>,
    /// The uniform elements 1..=`last` of an ARRAY, as one entry whose name still holds `{i}`.
    element: Option<Entry>,
    /// The highest sub-index.
    last: u8,
}

impl CatalogObject {
    /// The entry at `sub`.
    pub fn entry(&self, sub: u8) -> Option<Cow<'_, Entry>> {
        if let Some(e) = self.listed.get(&sub) {
            return Some(Cow::Borrowed(e));
        }
        let template = self
            .element
            .as_ref()
            .filter(|_| (1..=self.last).contains(&sub))?;
        let mut e = template.clone();
        e.sub = sub;
        e.description.name = e.description.name.fill("{i}", sub.into());
        Some(Cow::Owned(e))
    }

    /// Every entry, by sub-index.
    pub fn entries(&self) -> impl Iterator<Item = Cow<'_, Entry>> + '_ {
        (0..=self.last).filter_map(|sub| self.entry(sub))
    }

    /// The highest sub-index (0 for a VAR).
    pub fn last_sub(&self) -> u8 {
        self.last
    }
}

/// An entry as found for a concrete index: the lift-1 metadata and the lift it belongs to.
#[derive(Debug, Clone)]
pub struct Located<'a> {
    /// The metadata (indices are lift 1's).
    pub entry: Cow<'a, Entry>,
    /// The object.
    pub object: &'a CatalogObject,
    /// The lift (1 for objects that are not per lift).
    pub lift: u8,
    /// The index asked for.
    pub index: u16,
}

/// The whole catalog.
#[derive(Debug, Clone, PartialEq)]
pub struct Catalog {
    languages: Vec<String>,
    fallback: BTreeMap<String, String>,
    objects: BTreeMap<u16, CatalogObject>,
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

fn object_error(index: u16, reason: impl Into<String>) -> CatalogError {
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
    ) -> Result<Vec<CatalogObject>, CatalogError> {
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
            out.push(CatalogObject {
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

// ------------------------------------------------------------------------- the catalog

impl Catalog {
    /// Parse a catalog from its TOML text; objects must not overlap for any lift.
    pub fn from_toml(text: &str) -> Result<Catalog, CatalogError> {
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
        let catalog = Catalog {
            languages: raw.languages,
            fallback: raw.fallback,
            objects,
        };
        catalog.check_lift_collisions()?;
        Ok(catalog)
    }

    /// The catalog compiled into canlift (parsed on first use; `tests` prove it parses and
    /// validates, so a failure here is a build defect, not an input error).
    pub fn builtin() -> &'static Catalog {
        static BUILTIN: OnceLock<Catalog> = OnceLock::new();
        BUILTIN.get_or_init(|| match Catalog::from_toml(BUILTIN_TOML) {
            Ok(c) => c,
            Err(e) => panic!("the built-in catalog is broken: {e}"),
        })
    }

    /// The languages every text has.
    pub fn languages(&self) -> &[String] {
        &self.languages
    }

    /// The objects (lift 1).
    pub fn objects(&self) -> impl Iterator<Item = &CatalogObject> {
        self.objects.values()
    }

    /// The object at lift-1 index `index`.
    pub fn object(&self, index: u16) -> Option<&CatalogObject> {
        self.objects.get(&index)
    }

    /// Where object `o` lives for `lift`, if it exists for that lift.
    pub fn index_for_lift(o: &CatalogObject, lift: u8) -> Option<u16> {
        if lift == 1 {
            return Some(o.index);
        }
        if lift::lift_of(o.index).is_some() {
            return lift::for_lift(o.index, lift);
        }
        if o.per_lift && (1..=MAX_LIFTS).contains(&lift) {
            return o
                .index
                .checked_add(u16::from(lift - 1) * MANUFACTURER_LIFT_STRIDE);
        }
        None
    }

    /// The metadata of (`index`, `sub`) for any lift.
    pub fn lookup(&self, index: u16, sub: u8) -> Option<Located<'_>> {
        let (lift, object) = self.object_for(index)?;
        let entry = object.entry(sub)?;
        Some(Located {
            entry,
            object,
            lift,
            index,
        })
    }

    /// The object behind a concrete index, with its lift.
    pub fn object_for(&self, index: u16) -> Option<(u8, &CatalogObject)> {
        if let Some((lift, base)) = lift::lift_of(index) {
            return self.objects.get(&base).map(|o| (lift, o));
        }
        if let Some(o) = self.objects.get(&index) {
            return Some((1, o));
        }
        (1..MAX_LIFTS).find_map(|k| {
            let base = index.checked_sub(u16::from(k) * MANUFACTURER_LIFT_STRIDE)?;
            let o = self.objects.get(&base).filter(|o| o.per_lift)?;
            Some((k + 1, o))
        })
    }

    /// A text in the caller's language: `preferred`, then `alternate`, then the declared
    /// fallback of each, then English (NXg §6.1; docs/PROTOCOL.md §Languages). Returns
    /// (language, text).
    pub fn text<'a>(
        &'a self,
        texts: &'a Texts,
        preferred: &str,
        alternate: &str,
    ) -> Option<(&'a str, &'a str)> {
        let fallback = |l: &str| {
            self.fallback
                .iter()
                .find(|(k, _)| k.eq_ignore_ascii_case(l))
                .map(|(_, v)| v.as_str())
        };
        let (fp, fa) = (fallback(preferred), fallback(alternate));
        texts.first_of(
            [Some(preferred), Some(alternate), fp, fa, Some("en")]
                .into_iter()
                .flatten(),
        )
    }

    /// The object behind `index` on `device` (any device: `None`).
    fn object_on(&self, device: Option<Device>, index: u16) -> Option<&CatalogObject> {
        self.object_for(index)
            .map(|(_, o)| o)
            .filter(|o| device.is_none_or(|d| o.devices.contains(&d)))
    }

    /// What a gateway reports about (`index`, `sub`) of `device` built on this catalog (any
    /// device: `None`), for any lift (NXg §6.1.1).
    pub fn describe(&self, device: Option<Device>, index: u16, sub: u8) -> Lookup {
        if self.object_on(device, index).is_none() {
            return Lookup::NoObject;
        }
        match self.lookup(index, sub) {
            Some(found) => Lookup::Found(Box::new(found.entry.into_owned().description)),
            None => Lookup::NoSub,
        }
    }

    /// The name and hint of the whole object at `index` of `device` (any device: `None`), for
    /// a `compact` read (NXg §6.2).
    pub fn object_texts(&self, device: Option<Device>, index: u16) -> Option<(Texts, Texts)> {
        let object = self.object_on(device, index)?;
        Some((object.name.clone(), object.hint.clone()))
    }

    /// Every entry's name in every language (English first), for lift 1: what operators may
    /// type instead of an mplex (docs/PROTOCOL.md §Mplex).
    pub fn names(&self) -> ObjectNames {
        let mut names = ObjectNames::new();
        let languages = std::iter::once("en").chain(
            self.languages
                .iter()
                .map(String::as_str)
                .filter(|l| *l != "en"),
        );
        let languages: Vec<&str> = languages.collect();
        for object in self.objects() {
            for entry in object.entries() {
                let mplex = Mplex {
                    index: object.index,
                    sub: entry.sub,
                };
                for lang in &languages {
                    if let Some(name) = entry.description.name.get(lang) {
                        names.push(name, mplex);
                    }
                }
            }
        }
        names
    }

    fn check_lift_collisions(&self) -> Result<(), CatalogError> {
        let mut taken: BTreeMap<u16, (u16, u8)> = BTreeMap::new();
        for o in self.objects.values() {
            for lift in 1..=MAX_LIFTS {
                let Some(index) = Catalog::index_for_lift(o, lift) else {
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

    /// Everything wrong with the catalog's content: limits that do not fit the data type,
    /// lists that do not fit the range, texts missing a language without a declared fallback,
    /// forms that do not suit the type. Empty when the catalog is sound.
    pub fn validate(&self) -> Vec<String> {
        let mut problems = Vec::new();
        for (lang, to) in &self.fallback {
            if !self.languages.contains(to) {
                problems.push(format!("fallback {lang} → {to}: {to} is not complete"));
            }
        }
        for o in self.objects.values() {
            let at = |sub: Option<u8>| match sub {
                Some(s) => Entry::mplex(o.index, s),
                None => format!("{:04X}h", o.index),
            };
            self.check_texts(&o.name, &at(None), "name", &mut problems);
            self.check_texts(&o.hint, &at(None), "hint", &mut problems);
            if o.per_lift && lift::lift_of(o.index).is_some() {
                problems.push(format!("{}: per_lift on a CiA 417 object", at(None)));
            }
            if o.per_floor && o.code != ObjectCode::Array {
                problems.push(format!("{}: per_floor needs an ARRAY", at(None)));
            }
            for e in o.entries() {
                let here = at(Some(e.sub));
                let d = &e.description;
                self.check_texts(&d.name, &here, "name", &mut problems);
                self.check_texts(&d.hint, &here, "hint", &mut problems);
                for t in &d.list {
                    self.check_texts(t, &here, "list", &mut problems);
                }
                check_entry(&e, o.code, &here, &mut problems);
            }
        }
        problems
    }

    fn check_texts(&self, texts: &Texts, at: &str, what: &str, problems: &mut Vec<String>) {
        for lang in &self.languages {
            if texts.get(lang).is_none_or(str::is_empty) {
                problems.push(format!("{at}: {what} has no {lang} text"));
            }
        }
        for lang in texts.languages() {
            let known =
                self.languages.iter().any(|l| l == lang) || self.fallback.contains_key(lang);
            if !known {
                problems.push(format!(
                    "{at}: {what} in {lang}, a language with neither completeness nor fallback"
                ));
            }
        }
    }

    /// Build `device`'s object dictionary for `lifts` lifts (1–8) and `floors` floors (per-floor
    /// arrays get one element per floor). Values start at their defaults.
    pub fn dictionary(
        &self,
        device: Device,
        lifts: u8,
        floors: u8,
    ) -> Result<ObjectDictionary, CatalogError> {
        if !(1..=MAX_LIFTS).contains(&lifts) {
            return Err(object_error(
                0,
                format!("{lifts} lifts: 1 to 8 are possible"),
            ));
        }
        let mut od = ObjectDictionary::new();
        for o in self
            .objects
            .values()
            .filter(|o| o.devices.contains(&device))
        {
            let lift_count = if o.per_lift || lift::lift_of(o.index).is_some() {
                lifts
            } else {
                1
            };
            for lift in 1..=lift_count {
                let Some(index) = Catalog::index_for_lift(o, lift) else {
                    continue;
                };
                od.insert(build_object(o, index, lift, floors)?);
            }
        }
        Ok(od)
    }
}

fn check_entry(e: &Entry, code: ObjectCode, here: &str, problems: &mut Vec<String>) {
    let ty = e.value_type();
    let d = &e.description;
    let mut problem = |text: String| problems.push(format!("{here}: {text}"));
    let is_string = matches!(ty, DataType::VisibleString | DataType::UnicodeString);
    if let (Some(Bound::Int(lo)), Some(Bound::Int(hi))) = (d.min, d.max) {
        if lo > hi {
            problem(format!("min {lo} > max {hi}"));
        }
        if let Some((tlo, thi)) = ty.integer_range() {
            if lo < tlo || hi > thi {
                problem(format!("{lo}..={hi} does not fit {ty} ({tlo}..={thi})"));
            }
        } else if !is_string {
            problem(format!("integer limits on {ty}"));
        }
        let width = u32::try_from(ty.size().unwrap_or(0) * 8).unwrap_or(0);
        match d.formtype {
            FormType::Choice => {
                let wanted = hi - lo + 1;
                if d.list.len() as i128 != wanted {
                    problem(format!(
                        "a choice over {lo}..={hi} needs {wanted} list texts, has {}",
                        d.list.len()
                    ));
                }
            }
            FormType::Bits if d.list.len() > width as usize => {
                problem(format!("{} bit names for {width} bits", d.list.len()));
            }
            _ => {}
        }
    } else if d.min.is_some() != d.max.is_some() {
        problem("min without max or max without min".into());
    }
    if !matches!(d.formtype, FormType::Choice | FormType::Bits) && !d.list.is_empty() {
        problem(format!("a list on form {}", d.formtype));
    }
    let form_fits = match d.formtype {
        FormType::Text => is_string,
        FormType::Real => matches!(ty, DataType::Real32 | DataType::Real64),
        FormType::Switch => ty == DataType::Boolean || ty.is_unsigned(),
        FormType::Table => code == ObjectCode::Array,
        FormType::DateTime => matches!(ty, DataType::TimeOfDay | DataType::TimeDifference),
        FormType::Number | FormType::Duration | FormType::Choice | FormType::Bits => {
            ty.integer_range().is_some() || matches!(ty, DataType::Real32 | DataType::Real64)
        }
        FormType::Raw | FormType::Hex | FormType::Command => true,
    };
    if !form_fits {
        problem(format!("form {} does not suit {ty}", d.formtype));
    }
    if d.hints.show_off_at_zero && !(d.zero || d.min.is_some_and(|m| m.as_f64() <= 0.0)) {
        problem("show_off_at_zero, but 0 is not a valid value".into());
    }
    if d.zero && d.min.is_none_or(|m| m.as_f64() <= 0.0) {
        problem("zero is set, but 0 is inside the range anyway".into());
    }
    if let Some(text) = &e.default {
        match types::from_text(ty, text) {
            Err(err) => problem(format!("default {text:?}: {err}")),
            Ok(value) => {
                if let (Some(lo), Some(hi), Some(v)) = (d.min, d.max, value.as_f64()) {
                    let zero_ok = d.zero && v == 0.0;
                    if (v < lo.as_f64() || v > hi.as_f64()) && !zero_ok {
                        problem(format!("default {text} outside the limits"));
                    }
                }
            }
        }
    }
}

fn bound_value(ty: DataType, b: Bound) -> Option<Value> {
    match (b, ty) {
        (Bound::Int(v), t) if t.is_signed() => i64::try_from(v).ok().map(Value::Int),
        (Bound::Int(v), t) if t.is_unsigned() => u64::try_from(v).ok().map(Value::Uint),
        (Bound::Real(v), DataType::Real32) => Some(Value::Real32(v as f32)),
        (Bound::Real(v), DataType::Real64) => Some(Value::Real64(v)),
        _ => None,
    }
}

/// Refuses values between 0 and `min` for entries where 0 means "off" (the `zero` flag).
struct ZeroOrRange {
    ty: DataType,
    min: f64,
}

impl VariableHook for ZeroOrRange {
    fn on_write(&self, _: u16, _: u8, data: &[u8]) -> Result<(), AbortCode> {
        let value = types::decode(self.ty, data).map_err(|e| e.abort_code())?;
        match value.as_f64() {
            Some(v) if v != 0.0 && v < self.min => Err(AbortCode::VALUE_TOO_LOW),
            _ => Ok(()),
        }
    }
}

fn build_variable(e: &Entry, name: String) -> Result<Variable, CatalogError> {
    let ty = e.value_type();
    let d = &e.description;
    let access = match d.access {
        Access::Rw => od::Access::Rw,
        Access::Wo => od::Access::Wo,
        Access::Ro => od::Access::Ro,
        Access::Const => od::Access::Const,
    };
    let mut var = Variable::new(name, ty, access);
    if let Some(text) = &e.default {
        let value = types::from_text(ty, text)
            .map_err(|err| object_error(e.index, format!("sub {}: default: {err}", e.sub)))?;
        var = var.with_value(value);
    }
    if matches!(ty, DataType::VisibleString | DataType::UnicodeString) {
        var.max_len = d.max.and_then(|b| match b {
            Bound::Int(n) => usize::try_from(n).ok(),
            Bound::Real(_) => None,
        });
    } else if d.access.writable() {
        let low = match (d.zero, d.min) {
            (true, Some(min)) => {
                var = var.with_hook(Arc::new(ZeroOrRange {
                    ty,
                    min: min.as_f64(),
                }));
                bound_value(ty, Bound::Int(0))
            }
            (_, min) => min.and_then(|b| bound_value(ty, b)),
        };
        let high = d.max.and_then(|b| bound_value(ty, b));
        var = var.with_limits(low, high);
    }
    if e.pdo {
        var = var.mappable();
    }
    if e.persist {
        var = var.persistent();
    }
    Ok(var)
}

fn build_object(
    o: &CatalogObject,
    index: u16,
    lift: u8,
    floors: u8,
) -> Result<Object, CatalogError> {
    let suffix = if lift > 1 {
        format!(" (lift {lift})")
    } else {
        String::new()
    };
    let english = |t: &Texts| format!("{}{suffix}", t.get("en").unwrap_or_default());
    let last = if o.per_floor { floors.max(1) } else { o.last };
    let mut entries = Vec::new();
    for e in o.entries().filter(|e| e.sub <= last) {
        let mut var = build_variable(&e, english(&e.description.name))?;
        if e.sub == 0 && o.code != ObjectCode::Var {
            var = var.with_value(Value::Uint(last.into()));
        }
        entries.push((e.sub, var));
    }
    Ok(match o.code {
        ObjectCode::Var => {
            let (_, var) = entries
                .pop()
                .ok_or_else(|| object_error(o.index, "a VAR without entry"))?;
            Object::var(index, var)
        }
        code => Object::composite(index, english(&o.name), code, entries),
    })
}

#[cfg(test)]
mod tests;
