//! Compiles the built-in catalog, `catalog/lift.toml`, into static tables of numbers
//! (`$OUT_DIR/catalog_tables.rs`, included by `src/catalog.rs`): read by the same modules that
//! read a vendor metadata file at run time, so a catalog that would not load does not build.
//! The tables hold no pointers, so the linker puts them in read-only pages and nothing is
//! relocated, parsed or allocated for them when canlift starts.

// The build script compiles three of the library's modules and uses the part that reads a
// catalog and makes its tables; the lookups are the library's.
#![allow(dead_code)]

#[path = "src/lift.rs"]
mod lift;
#[path = "src/catalog/source.rs"]
mod source;
#[path = "src/catalog/tables.rs"]
mod tables;

use std::fmt::Write as _;

use nxg::meta::Bound;
use tables::{EntryRow, ObjectRow, Tables, TextTables};

const CATALOG: &str = "catalog/lift.toml";

fn main() {
    for input in [
        CATALOG,
        "build.rs",
        "src/lift.rs",
        "src/catalog/source.rs",
        "src/catalog/tables.rs",
    ] {
        println!("cargo::rerun-if-changed={input}");
    }
    let text = std::fs::read_to_string(CATALOG).unwrap_or_else(|e| panic!("{CATALOG}: {e}"));
    let source = match source::Source::parse(&text) {
        Ok(source) => source,
        Err(e) => panic!("{}", e.located(CATALOG, &text)),
    };
    let tables = tables::Builder::build(&source);
    let mut out = String::new();
    emit(&mut out, &source, &tables).unwrap_or_else(|e| panic!("formatting the tables: {e}"));
    let dir = std::env::var("OUT_DIR").unwrap_or_else(|e| panic!("OUT_DIR: {e}"));
    let path = std::path::Path::new(&dir).join("catalog_tables.rs");
    std::fs::write(&path, out).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
}

/// The tables as Rust items. Debug formatting of the plain rows ([`tables::Span`],
/// `PooledText`, `Hints`) is their Rust expression; enums are written with their type.
fn emit(out: &mut String, source: &source::Source, t: &Tables) -> std::fmt::Result {
    writeln!(out, "// Written by build.rs from {CATALOG}: do not edit.")?;
    writeln!(
        out,
        "pub(super) const LANGUAGES: &[&str] = &{:?};",
        source.languages
    )?;
    let fallback: Vec<(&str, &str)> = source
        .fallback
        .iter()
        .map(|(from, to)| (from.as_str(), to.as_str()))
        .collect();
    writeln!(
        out,
        "pub(super) const FALLBACK: &[(&str, &str)] = &{fallback:?};"
    )?;
    let (pool, pairs) = match &t.text {
        TextTables::Shared(pool) => (&*pool.strings, &*pool.pairs),
        TextTables::Static { pool, pairs } => (*pool, *pairs),
    };
    writeln!(out, "pub(super) static POOL: &str = {pool:?};")?;
    array(out, "PAIRS", "PooledText", pairs, |out, p| {
        writeln!(out, "    {p:?},")
    })?;
    array(out, "LISTS", "Span", &t.lists, |out, s| {
        writeln!(out, "    {s:?},")
    })?;
    array(out, "ENTRIES", "EntryRow", &t.entries, entry)?;
    array(out, "OBJECTS", "ObjectRow", &t.objects, object)
}

/// `pub(super) static NAME: [TYPE; N] = [ … ];`, a row per item.
fn array<T>(
    out: &mut String,
    name: &str,
    ty: &str,
    items: &[T],
    row: impl Fn(&mut String, &T) -> std::fmt::Result,
) -> std::fmt::Result {
    writeln!(out, "pub(super) static {name}: [{ty}; {}] = [", items.len())?;
    for item in items {
        row(out, item)?;
    }
    writeln!(out, "];")
}

fn bound(b: Option<Bound>) -> String {
    match b {
        None => "None".into(),
        Some(Bound::Int(v)) => format!("Some(Bound::Int({v}))"),
        Some(Bound::Real(v)) => format!("Some(Bound::Real({v:?}))"),
    }
}

fn entry(out: &mut String, e: &EntryRow) -> std::fmt::Result {
    writeln!(
        out,
        "    EntryRow {{ index: {:#06x}, sub: {}, objcode: ObjCode::{:?}, \
         datatype: match DataType::from_code({}) {{ Ok(t) => t, Err(_) => panic!() }}, \
         formtype: FormType::{:?}, physunit: PhysUnit::{:?}, access: Access::{:?}, \
         privilege: Privilege::{:?}, name: {:?}, hint: {:?}, min: {}, max: {}, zero: {}, \
         list: {:?}, hints: {:?}, default: {:?}, pdo: {}, persist: {} }},",
        e.index,
        e.sub,
        e.objcode,
        e.datatype.code(),
        e.formtype,
        e.physunit,
        e.access,
        e.privilege,
        e.name,
        e.hint,
        bound(e.min),
        bound(e.max),
        e.zero,
        e.list,
        e.hints,
        e.default,
        e.pdo,
        e.persist
    )
}

fn object(out: &mut String, o: &ObjectRow) -> std::fmt::Result {
    writeln!(
        out,
        "    ObjectRow {{ index: {:#06x}, code: ObjectCode::{:?}, devices: {}, per_lift: {}, \
         per_floor: {}, name: {:?}, hint: {:?}, listed: {:?}, element: {:?}, last: {} }},",
        o.index,
        o.code,
        o.devices,
        o.per_lift,
        o.per_floor,
        o.name,
        o.hint,
        o.listed,
        o.element,
        o.last
    )
}
