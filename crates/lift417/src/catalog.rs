//! The object catalog: every object a canlift lift controller (and its I/O node) holds, with the
//! metadata `get_canopen_object` reports (NXg SW003 §6.1): object code, data type, form, unit,
//! access, privilege, names and hints per language, limits, lists and presentation hints.
//!
//! The data lives in `catalog/lift.toml`. `build.rs` reads it with the same code that reads a
//! vendor metadata file at run time ([`Catalog::from_toml`]) and compiles it into static tables
//! of numbers (`tables`): the built-in catalog ([`Catalog::builtin`]) sits in read-only pages
//! that every canlift process shares, and nothing is parsed at start. Lookups build the
//! [`Entry`] they answer from the tables.
//!
//! Objects are described for lift 1. The lift-number rule of CiA 417-4 §4.1.1 (lift n at
//! +(n − 1) × 800h, see [`crate::lift`]) and ours for manufacturer objects marked `per_lift`
//! (lift n at +(n − 1) × [`MANUFACTURER_LIFT_STRIDE`]) are applied here, by code:
//! [`Catalog::lookup`] answers for any lift, [`Catalog::dictionary`] builds a device's object
//! dictionary for any number of lifts.

use std::borrow::Cow;
use std::collections::BTreeMap;
use std::sync::{Arc, OnceLock};

use canopen::od::{self, Object, ObjectCode, ObjectDictionary, Variable, VariableHook};
use canopen::sdo::abort::AbortCode;
use canopen::types::{self, DataType, Value};
use nxg::gateway::Lookup;
use nxg::meta::{Access, Bound, FormType, Texts};
use nxg::mplex::Mplex;
use nxg::names::ObjectNames;

use crate::lift::{self, MAX_LIFTS};

mod source;
mod tables;

use source::object_error;
pub use source::{CatalogError, Device, Entry, MANUFACTURER_LIFT_STRIDE};
use tables::{device_bit, EntryRow, ObjectRow, Tables};

/// The built-in catalog's tables, written by `build.rs` from `catalog/lift.toml`.
mod builtin {
    use super::tables::{EntryRow, ObjectRow, Span};
    use canopen::od::ObjectCode;
    use nxg::meta::Privilege;
    use nxg::meta::{Access, Bound, DataType, FormType, Hints, ObjCode, PhysUnit, PooledText};

    include!(concat!(env!("OUT_DIR"), "/catalog_tables.rs"));
}

/// One catalog object (lift 1): a view of the tables that builds its texts and entries when
/// asked.
#[derive(Debug, Clone, Copy)]
pub struct CatalogObject<'a> {
    tables: &'a Tables,
    row: &'a ObjectRow,
}

impl<'a> CatalogObject<'a> {
    /// Index (lift 1).
    pub fn index(&self) -> u16 {
        self.row.index
    }

    /// Object code.
    pub fn code(&self) -> ObjectCode {
        self.row.code
    }

    /// Name per language.
    pub fn name(&self) -> Texts {
        self.tables.texts(self.row.name)
    }

    /// Hint per language.
    pub fn hint(&self) -> Texts {
        self.tables.texts(self.row.hint)
    }

    /// Whether `device` holds the object.
    pub fn held_by(&self, device: Device) -> bool {
        self.row.devices & device_bit(device) != 0
    }

    /// A manufacturer object repeated for every lift.
    pub fn per_lift(&self) -> bool {
        self.row.per_lift
    }

    /// An array with one element per floor (the device sizes it by its number of floors).
    pub fn per_floor(&self) -> bool {
        self.row.per_floor
    }

    /// The row of the entry at `sub` and whether it is the uniform element standing in for it.
    fn row_of(&self, sub: u8) -> Option<(&'a EntryRow, bool)> {
        let listed = self.tables.listed(self.row);
        if let Ok(at) = listed.binary_search_by_key(&sub, |e| e.sub) {
            return listed.get(at).map(|e| (e, false));
        }
        let element = self.tables.element(self.row)?;
        (1..=self.row.last)
            .contains(&sub)
            .then_some((element, true))
    }

    /// The entry at `sub`.
    pub fn entry(&self, sub: u8) -> Option<Entry> {
        let (row, uniform) = self.row_of(sub)?;
        let mut e = self.tables.entry(row);
        if uniform {
            e.sub = sub;
            e.description.name = e.description.name.fill("{i}", sub.into());
        }
        Some(e)
    }

    /// Every entry, by sub-index.
    pub fn entries(self) -> impl Iterator<Item = Entry> + 'a {
        (0..=self.row.last).filter_map(move |sub| self.entry(sub))
    }

    /// The highest sub-index (0 for a VAR).
    pub fn last_sub(&self) -> u8 {
        self.row.last
    }
}

/// An entry as found for a concrete index: the lift-1 metadata and the lift it belongs to.
#[derive(Debug, Clone)]
pub struct Located<'a> {
    /// The metadata (indices are lift 1's).
    pub entry: Entry,
    /// The object.
    pub object: CatalogObject<'a>,
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
    tables: Tables,
}

// ------------------------------------------------------------------------- the catalog

impl Catalog {
    /// Read a catalog from its TOML text; objects must not overlap for any lift.
    pub fn from_toml(text: &str) -> Result<Catalog, CatalogError> {
        let source = source::Source::parse(text)?;
        Ok(Catalog {
            tables: tables::Builder::build(&source),
            languages: source.languages,
            fallback: source.fallback,
        })
    }

    /// The catalog compiled into canlift: static tables, not parsed (`build.rs` refuses to
    /// build with a catalog that does not read; `tests` prove the tables equal what
    /// [`Catalog::from_toml`] makes of the same text, and that the catalog validates).
    pub fn builtin() -> &'static Catalog {
        static BUILTIN: OnceLock<Catalog> = OnceLock::new();
        BUILTIN.get_or_init(|| Catalog {
            languages: builtin::LANGUAGES.iter().map(|&l| l.to_owned()).collect(),
            fallback: builtin::FALLBACK
                .iter()
                .map(|&(from, to)| (from.to_owned(), to.to_owned()))
                .collect(),
            tables: Tables {
                text: tables::TextTables::Static {
                    pool: builtin::POOL,
                    pairs: &builtin::PAIRS,
                },
                lists: Cow::Borrowed(&builtin::LISTS),
                entries: Cow::Borrowed(&builtin::ENTRIES),
                objects: Cow::Borrowed(&builtin::OBJECTS),
            },
        })
    }

    /// The languages every text has.
    pub fn languages(&self) -> &[String] {
        &self.languages
    }

    fn view<'a>(&'a self, row: &'a ObjectRow) -> CatalogObject<'a> {
        CatalogObject {
            tables: &self.tables,
            row,
        }
    }

    /// The objects (lift 1), by index.
    pub fn objects(&self) -> impl Iterator<Item = CatalogObject<'_>> {
        self.tables.objects.iter().map(|row| self.view(row))
    }

    /// The object at lift-1 index `index`.
    pub fn object(&self, index: u16) -> Option<CatalogObject<'_>> {
        self.tables.object(index).map(|row| self.view(row))
    }

    /// Where object `o` lives for `lift`, if it exists for that lift.
    pub fn index_for_lift(o: &CatalogObject, lift: u8) -> Option<u16> {
        source::index_for_lift(o.index(), o.per_lift(), lift)
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
    pub fn object_for(&self, index: u16) -> Option<(u8, CatalogObject<'_>)> {
        if let Some((lift, base)) = lift::lift_of(index) {
            return self.object(base).map(|o| (lift, o));
        }
        if let Some(o) = self.object(index) {
            return Some((1, o));
        }
        (1..MAX_LIFTS).find_map(|k| {
            let base = index.checked_sub(u16::from(k) * MANUFACTURER_LIFT_STRIDE)?;
            let o = self.object(base).filter(|o| o.per_lift())?;
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
    fn object_on(&self, device: Option<Device>, index: u16) -> Option<CatalogObject<'_>> {
        self.object_for(index)
            .map(|(_, o)| o)
            .filter(|o| device.is_none_or(|d| o.held_by(d)))
    }

    /// What a gateway reports about (`index`, `sub`) of `device` built on this catalog (any
    /// device: `None`), for any lift (NXg §6.1.1).
    pub fn describe(&self, device: Option<Device>, index: u16, sub: u8) -> Lookup {
        let Some(object) = self.object_on(device, index) else {
            return Lookup::NoObject;
        };
        match object.entry(sub) {
            Some(entry) => Lookup::Found(Box::new(entry.description)),
            None => Lookup::NoSub,
        }
    }

    /// The name and hint of the whole object at `index` of `device` (any device: `None`), for
    /// a `compact` read (NXg §6.2).
    pub fn object_texts(&self, device: Option<Device>, index: u16) -> Option<(Texts, Texts)> {
        let object = self.object_on(device, index)?;
        Some((object.name(), object.hint()))
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
                    index: object.index(),
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
        for o in self.objects() {
            let at = |sub: Option<u8>| match sub {
                Some(s) => Entry::mplex(o.index(), s),
                None => format!("{:04X}h", o.index()),
            };
            self.check_texts(&o.name(), &at(None), "name", &mut problems);
            self.check_texts(&o.hint(), &at(None), "hint", &mut problems);
            if o.per_lift() && lift::lift_of(o.index()).is_some() {
                problems.push(format!("{}: per_lift on a CiA 417 object", at(None)));
            }
            if o.per_floor() && o.code() != ObjectCode::Array {
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
                check_entry(&e, o.code(), &here, &mut problems);
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
            return Err(CatalogError::Object {
                index: 0,
                reason: format!("{lifts} lifts: 1 to 8 are possible"),
            });
        }
        let mut od = ObjectDictionary::new();
        for o in self.objects().filter(|o| o.held_by(device)) {
            let lift_count = if o.per_lift() || lift::lift_of(o.index()).is_some() {
                lifts
            } else {
                1
            };
            for lift in 1..=lift_count {
                let Some(index) = Catalog::index_for_lift(&o, lift) else {
                    continue;
                };
                od.insert(build_object(&o, index, lift, floors)?);
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
    let last = if o.per_floor() {
        floors.max(1)
    } else {
        o.last_sub()
    };
    let mut entries = Vec::new();
    for e in (0..=last).filter_map(|sub| o.entry(sub)) {
        let mut var = build_variable(&e, english(&e.description.name))?;
        if e.sub == 0 && o.code() != ObjectCode::Var {
            var = var.with_value(Value::Uint(last.into()));
        }
        entries.push((e.sub, var));
    }
    Ok(match o.code() {
        ObjectCode::Var => {
            let (_, var) = entries
                .pop()
                .ok_or_else(|| object_error(o.index(), "a VAR without entry"))?;
            Object::var(index, var)
        }
        code => Object::composite(index, english(&o.name()), code, entries),
    })
}

#[cfg(test)]
mod tests;
