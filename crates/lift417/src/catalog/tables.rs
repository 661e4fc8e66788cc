//! The catalog as tables of numbers: objects, entries, text pairs and list items refer to each
//! other and to one string pool by position, never by pointer. `build.rs` writes the built-in
//! catalog's tables as `static` arrays, which the linker puts in read-only pages shared by every
//! canlift process and that nothing parses at start; a vendor metadata file read at run time
//! becomes the same tables, owned.

use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::Arc;

use canopen::od::ObjectCode;
use nxg::meta::{Access, Bound, DataType, Description, FormType, Hints, ObjCode, PhysUnit};
use nxg::meta::{PooledText, Privilege, TextPool, Texts};

use super::source::{Device, Entry, ObjectDef, Source};

/// A run of `len` items from `start` in one of the tables (bytes of the pool for a string).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub(crate) struct Span {
    pub start: u32,
    pub len: u32,
}

impl Span {
    fn range(self) -> std::ops::Range<usize> {
        let start = self.start as usize;
        start..start + self.len as usize
    }
}

/// One sub-object (lift 1) with its metadata; texts are spans of `pairs`, the list a span of
/// `lists`, the default a string of the pool.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct EntryRow {
    pub index: u16,
    pub sub: u8,
    pub objcode: ObjCode,
    pub datatype: DataType,
    pub formtype: FormType,
    pub physunit: PhysUnit,
    pub access: Access,
    pub privilege: Privilege,
    pub name: Span,
    pub hint: Span,
    pub min: Option<Bound>,
    pub max: Option<Bound>,
    pub zero: bool,
    pub list: Span,
    pub hints: Hints,
    pub default: Option<Span>,
    pub pdo: bool,
    pub persist: bool,
}

/// One object (lift 1): its listed entries are a span of `entries` in sub-index order, the
/// uniform element of an ARRAY one more entry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct ObjectRow {
    pub index: u16,
    pub code: ObjectCode,
    /// [`device_bit`]s of the devices that hold it.
    pub devices: u8,
    pub per_lift: bool,
    pub per_floor: bool,
    pub name: Span,
    pub hint: Span,
    pub listed: Span,
    pub element: Option<u32>,
    pub last: u8,
}

/// The bit of `device` in [`ObjectRow::devices`].
pub(crate) fn device_bit(device: Device) -> u8 {
    match device {
        Device::Controller => 1,
        Device::Io => 2,
    }
}

/// A catalog's strings (`pool`, each once) and the (language, text) pairs of its [`Texts`] (a
/// span per `Texts`): `static`s for the built-in catalog, shared for one read at run time — a
/// description's texts point into them either way, nothing is copied.
#[derive(Debug, Clone)]
pub(crate) enum TextTables {
    /// The built-in catalog's.
    Static {
        pool: &'static str,
        pairs: &'static [PooledText],
    },
    /// Read at run time (a vendor's metadata file).
    Shared(Arc<TextPool>),
}

impl TextTables {
    /// Every string, each once.
    pub fn pool(&self) -> &str {
        self.parts().0
    }

    fn parts(&self) -> (&str, &[PooledText]) {
        match self {
            TextTables::Static { pool, pairs } => (pool, pairs),
            TextTables::Shared(pool) => (&pool.strings, &pool.pairs),
        }
    }
}

/// The same tables, static or shared.
impl PartialEq for TextTables {
    fn eq(&self, other: &TextTables) -> bool {
        self.parts() == other.parts()
    }
}

/// A catalog's tables: borrowed from `static`s for the built-in catalog, owned for one read
/// at run time.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Tables {
    /// The strings and the texts' pairs.
    pub text: TextTables,
    /// The items of every list, each a span of `pairs`.
    pub lists: Cow<'static, [Span]>,
    /// The entries, object after object.
    pub entries: Cow<'static, [EntryRow]>,
    /// The objects by index.
    pub objects: Cow<'static, [ObjectRow]>,
}

impl Tables {
    /// The string at `s` (empty if the tables were inconsistent, which [`Builder`] rules out).
    pub fn str(&self, s: Span) -> &str {
        self.text.pool().get(s.range()).unwrap_or_default()
    }

    /// The texts at `t`: a view of the tables, static or shared.
    pub fn texts(&self, t: Span) -> Texts {
        match &self.text {
            TextTables::Static { pool, pairs } => {
                Texts::pooled(pool, pairs.get(t.range()).unwrap_or_default())
            }
            TextTables::Shared(pool) => Texts::shared_pool(pool, t.start, t.len),
        }
    }

    /// The object at lift-1 index `index`.
    pub fn object(&self, index: u16) -> Option<&ObjectRow> {
        let at = self
            .objects
            .binary_search_by_key(&index, |o| o.index)
            .ok()?;
        self.objects.get(at)
    }

    /// The listed entries of `o`, by sub-index.
    pub fn listed(&self, o: &ObjectRow) -> &[EntryRow] {
        self.entries.get(o.listed.range()).unwrap_or_default()
    }

    /// The uniform element of `o`, if it has one.
    pub fn element(&self, o: &ObjectRow) -> Option<&EntryRow> {
        self.entries.get(o.element? as usize)
    }

    /// The entry a row describes, with its texts.
    pub fn entry(&self, row: &EntryRow) -> Entry {
        let items = self.lists.get(row.list.range()).unwrap_or_default();
        Entry {
            index: row.index,
            sub: row.sub,
            description: Description {
                objcode: row.objcode,
                datatype: row.datatype,
                formtype: row.formtype,
                physunit: row.physunit,
                access: row.access,
                privilege: row.privilege,
                name: self.texts(row.name),
                hint: self.texts(row.hint),
                min: row.min,
                max: row.max,
                zero: row.zero,
                list: items.iter().map(|&t| self.texts(t)).collect(),
                hints: row.hints,
            },
            default: row.default.map(|d| self.str(d).to_owned()),
            pdo: row.pdo,
            persist: row.persist,
        }
    }
}

/// Builds [`Tables`] from a [`Source`], storing each string and each set of texts once.
#[derive(Default)]
pub(crate) struct Builder {
    pool: String,
    pairs: Vec<PooledText>,
    lists: Vec<Span>,
    entries: Vec<EntryRow>,
    objects: Vec<ObjectRow>,
    strings: HashMap<String, Span>,
    texts: HashMap<Vec<PooledText>, Span>,
}

/// A span from `start` to the end of a table of `end` items. Tables stay far below 4 Gi items:
/// the text they come from is read into memory whole.
fn span(start: usize, end: usize) -> Span {
    Span {
        start: start as u32,
        len: (end - start) as u32,
    }
}

impl Builder {
    /// The tables of `source`.
    pub fn build(source: &Source) -> Tables {
        let mut b = Builder::default();
        for o in source.objects.values() {
            b.object(o);
        }
        Tables {
            text: TextTables::Shared(Arc::new(TextPool {
                strings: b.pool.into(),
                pairs: b.pairs.into(),
            })),
            lists: Cow::Owned(b.lists),
            entries: Cow::Owned(b.entries),
            objects: Cow::Owned(b.objects),
        }
    }

    fn str(&mut self, s: &str) -> Span {
        if let Some(&at) = self.strings.get(s) {
            return at;
        }
        let start = self.pool.len();
        self.pool.push_str(s);
        let at = span(start, self.pool.len());
        self.strings.insert(s.to_owned(), at);
        at
    }

    fn texts(&mut self, t: &Texts) -> Span {
        let pairs: Vec<PooledText> = t
            .pairs()
            .map(|(lang, text)| {
                let (lang, text) = (self.str(lang), self.str(text));
                PooledText {
                    lang_start: lang.start,
                    lang_len: lang.len,
                    text_start: text.start,
                    text_len: text.len,
                }
            })
            .collect();
        if let Some(&at) = self.texts.get(&pairs) {
            return at;
        }
        let start = self.pairs.len();
        self.pairs.extend_from_slice(&pairs);
        let at = span(start, self.pairs.len());
        self.texts.insert(pairs, at);
        at
    }

    fn entry(&mut self, e: &Entry) -> EntryRow {
        let d = &e.description;
        let items: Vec<Span> = d.list.iter().map(|t| self.texts(t)).collect();
        let start = self.lists.len();
        self.lists.extend(items);
        EntryRow {
            index: e.index,
            sub: e.sub,
            objcode: d.objcode,
            datatype: d.datatype,
            formtype: d.formtype,
            physunit: d.physunit,
            access: d.access,
            privilege: d.privilege,
            name: self.texts(&d.name),
            hint: self.texts(&d.hint),
            min: d.min,
            max: d.max,
            zero: d.zero,
            list: span(start, self.lists.len()),
            hints: d.hints,
            default: e.default.as_deref().map(|s| self.str(s)),
            pdo: e.pdo,
            persist: e.persist,
        }
    }

    fn object(&mut self, o: &ObjectDef) {
        let rows: Vec<EntryRow> = o.listed.values().map(|e| self.entry(e)).collect();
        let start = self.entries.len();
        self.entries.extend(rows);
        let listed = span(start, self.entries.len());
        let element = o.element.as_ref().map(|e| {
            let row = self.entry(e);
            self.entries.push(row);
            (self.entries.len() - 1) as u32
        });
        let row = ObjectRow {
            index: o.index,
            code: o.code,
            devices: o.devices.iter().fold(0, |bits, &d| bits | device_bit(d)),
            per_lift: o.per_lift,
            per_floor: o.per_floor,
            name: self.texts(&o.name),
            hint: self.texts(&o.hint),
            listed,
            element,
            last: o.last,
        };
        self.objects.push(row);
    }
}
