//! CiA 306 electronic data sheets (EDS) and device configuration files (DCF): import into an
//! [`ObjectDictionary`] and export back.
//!
//! Import accepts what tools write in practice: keys and section names in any case, `;` comments,
//! decimal, `0x` hex and leading-zero octal numbers, `$NODEID` formulas in either order
//! (`$NODEID+0x180`, `0x180 + $NODEID`), `CompactSubObj` arrays with their `[xxxxName]` and
//! `[xxxxValue]` sections, `ObjectLinks`, `DummyUsage`, the `DeviceComissioning` section under
//! its common spellings, and DCF `ParameterValue` / `Denotation`, in UTF-8 or (as Windows tools
//! write them) Windows-1252.
//!
//! Import is as tolerant as the files in the field need and as strict as safety needs: a defect
//! of the file (a count that does not match, a listed object without its section, a default that
//! is no value of its type, an undefined data type, a duplicate key) is a [`Finding`] naming the
//! file and line, and only the defective part is left out — a sub-object without a usable type,
//! an object without a usable sub-object; a sub-object whose limits cannot be read is kept
//! read-only, so nothing without a usable description is ever written. Only a file without any
//! usable object is refused ([`EdsError`]). Export writes the expanded form (one section per
//! sub-object), so import → export → import gives the same dictionary.

use std::cell::RefCell;
use std::collections::{BTreeMap, HashMap};
use std::fmt::{self, Write as _};

use crate::od::{Access, Object, ObjectCode, ObjectDictionary, Variable};
use crate::types::{self, DataType, Value};

/// How much of a file a [`Finding`] cost.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Severity {
    /// The file says something wrongly, and it was taken as meant (a count, a duplicate, a
    /// default value dropped, the text's encoding).
    Warning,
    /// A part of the file is left out (an object or sub-object), or kept read-only.
    Error,
}

impl Severity {
    /// `warning` or `error`.
    pub fn name(self) -> &'static str {
        match self {
            Severity::Warning => "warning",
            Severity::Error => "error",
        }
    }
}

/// A defect of an EDS or DCF (CiA 306) and what import made of it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Finding {
    /// The file name as given.
    pub file: String,
    /// 1-based line number (0 for the file as a whole).
    pub line: usize,
    /// What it cost.
    pub severity: Severity,
    /// What is wrong, and what was done.
    pub message: String,
}

impl fmt::Display for Finding {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}:{}: {}: {}",
            self.file,
            self.line,
            self.severity.name(),
            self.message
        )
    }
}

/// An imported file and what was wrong with it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Imported {
    /// What the file describes, the defective parts left out.
    pub description: DeviceDescription,
    /// Its defects, in the order of the file.
    pub findings: Vec<Finding>,
}

impl Imported {
    /// The description, each finding logged as a warning: for those that go on with what the
    /// file describes well (a gateway serving its node, a tool decoding its frames).
    pub fn logged(self) -> DeviceDescription {
        for finding in &self.findings {
            tracing::warn!(%finding, "device description");
        }
        self.description
    }
}

/// Why a file could not be imported at all.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{file}:{line}: {reason}")]
pub struct EdsError {
    /// The file name as given.
    pub file: String,
    /// 1-based line number (0 when the problem is the file as a whole).
    pub line: usize,
    /// What is wrong.
    pub reason: String,
}

/// The spellings of the commissioning section found in the field (CiA 306 itself writes
/// "DeviceComissioning").
const COMMISSIONING: [&str; 4] = [
    "devicecomissioning",
    "devicecommissioning",
    "devicecomissionning",
    "devicecommisioning",
];

/// `[DeviceComissioning]` of a DCF.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Commissioning {
    /// Node-ID the configuration is for.
    pub node_id: Option<u8>,
    /// Node name.
    pub node_name: Option<String>,
    /// Bit rate in kbit/s.
    pub baudrate: Option<u32>,
    /// Other keys, as written.
    pub other: Vec<(String, String)>,
}

/// An imported EDS or DCF: the dictionary plus the descriptive sections, kept for export.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct DeviceDescription {
    /// `[FileInfo]` entries in file order.
    pub file_info: Vec<(String, String)>,
    /// `[DeviceInfo]` entries in file order.
    pub device_info: Vec<(String, String)>,
    /// `[DummyUsage]` entries.
    pub dummy_usage: Vec<(String, String)>,
    /// `[Comments]` lines.
    pub comments: Vec<String>,
    /// `[DeviceComissioning]`, present in DCFs.
    pub commissioning: Option<Commissioning>,
    /// Object links: object index → linked indices.
    pub object_links: BTreeMap<u16, Vec<u16>>,
    /// The object dictionary, values evaluated for the node-ID.
    pub od: ObjectDictionary,
}

struct Entry {
    key: String,
    value: String,
    line: usize,
}

struct Section {
    name: String,
    line: usize,
    entries: Vec<Entry>,
}

impl Section {
    fn get(&self, key: &str) -> Option<&Entry> {
        self.entries
            .iter()
            .find(|e| e.key.eq_ignore_ascii_case(key))
    }
}

/// The findings of one import, each naming the file.
struct Findings<'a> {
    file: &'a str,
    list: RefCell<Vec<Finding>>,
}

impl Findings<'_> {
    fn add(&self, line: usize, severity: Severity, message: impl Into<String>) {
        self.list.borrow_mut().push(Finding {
            file: self.file.to_owned(),
            line,
            severity,
            message: message.into(),
        });
    }

    fn warn(&self, line: usize, message: impl Into<String>) {
        self.add(line, Severity::Warning, message);
    }

    /// A part left out because of `e`.
    fn left_out(&self, e: EdsError) {
        self.add(e.line, Severity::Error, e.reason);
    }
}

struct Ini<'a> {
    file: &'a str,
    sections: Vec<Section>,
    by_name: HashMap<String, usize>,
}

impl<'a> Ini<'a> {
    /// The sections of `text`; what is not INI (a line without `=`, an entry before the first
    /// section, a repeated section or key) is a finding and passed over — the first of two
    /// sections or keys of one name counts.
    fn parse(file: &'a str, text: &str, findings: &Findings) -> Self {
        let mut ini = Ini {
            file,
            sections: Vec::new(),
            by_name: HashMap::new(),
        };
        // Where entries go: a section's index; none before the first and in a repeated one.
        let mut current: Option<usize> = None;
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        for (n, raw) in text.lines().enumerate() {
            let line = n + 1;
            let trimmed = raw.trim();
            if trimmed.is_empty() || trimmed.starts_with(';') || trimmed.starts_with('#') {
                continue;
            }
            if let Some(rest) = trimmed.strip_prefix('[') {
                current = None;
                let Some(name) = rest.strip_suffix(']').map(str::trim) else {
                    findings.warn(
                        line,
                        "section header without closing ']': its entries are passed over",
                    );
                    continue;
                };
                let key = name.to_ascii_lowercase();
                if let Some(&first) = ini.by_name.get(&key) {
                    findings.warn(
                        line,
                        format!(
                            "section [{name}] appears twice (first at line {}): the second is passed over",
                            ini.sections[first].line
                        ),
                    );
                    continue;
                }
                current = Some(ini.sections.len());
                ini.by_name.insert(key, ini.sections.len());
                ini.sections.push(Section {
                    name: name.to_owned(),
                    line,
                    entries: Vec::new(),
                });
                continue;
            }
            let Some((key, value)) = trimmed.split_once('=') else {
                findings.warn(
                    line,
                    format!("expected KEY=VALUE, found {trimmed:?}: passed over"),
                );
                continue;
            };
            let Some(section) = current.and_then(|i| ini.sections.get_mut(i)) else {
                if ini.sections.is_empty() {
                    findings.warn(line, "entry before the first [section]: passed over");
                }
                continue;
            };
            let key = key.trim();
            if let Some(first) = section.get(key) {
                findings.warn(
                    line,
                    format!(
                        "key {key} appears twice in [{}] (first at line {}): the second is passed over",
                        section.name, first.line
                    ),
                );
                continue;
            }
            section.entries.push(Entry {
                key: key.to_owned(),
                value: value.trim().to_owned(),
                line,
            });
        }
        ini
    }

    fn error(&self, line: usize, reason: impl Into<String>) -> EdsError {
        EdsError {
            file: self.file.to_owned(),
            line,
            reason: reason.into(),
        }
    }

    fn section(&self, name: &str) -> Option<&Section> {
        self.by_name
            .get(&name.to_ascii_lowercase())
            .map(|&i| &self.sections[i])
    }

    fn pairs(&self, name: &str) -> Vec<(String, String)> {
        self.section(name)
            .map(|s| {
                s.entries
                    .iter()
                    .map(|e| (e.key.clone(), e.value.clone()))
                    .collect()
            })
            .unwrap_or_default()
    }
}

/// Evaluate a number that may use `$NODEID` (`$NODEID+0x180`, `0x180+$NODEID`).
fn eval_number(text: &str, node_id: u8) -> Option<i128> {
    let mut total: i128 = 0;
    for term in text.split('+') {
        let term = term.trim();
        total += if term.eq_ignore_ascii_case("$NODEID") {
            i128::from(node_id)
        } else {
            types::parse_integer(term)?
        };
    }
    Some(total)
}

/// The value of `text` as `ty` for `node_id` (numbers may use `$NODEID` and any EDS base).
fn eval_value(ty: DataType, text: &str, node_id: u8) -> Option<Value> {
    if ty.integer_range().is_some() && ty != DataType::Boolean {
        let v = if text.is_empty() {
            0
        } else {
            eval_number(text, node_id)?
        };
        let (lo, hi) = ty.integer_range()?;
        // Unsigned values are often written as their two's complement hex (0xFFFFFFFF for -1 in
        // INTEGER32 is an error, but the reverse is common); keep only in-range values.
        if !(lo..=hi).contains(&v) {
            return None;
        }
        return Some(if ty.is_signed() {
            Value::Int(v as i64)
        } else {
            Value::Uint(v as u64)
        });
    }
    match ty {
        DataType::Boolean if text.is_empty() => Some(Value::Bool(false)),
        DataType::Boolean => match eval_number(text, node_id)? {
            0 => Some(Value::Bool(false)),
            1 => Some(Value::Bool(true)),
            _ => None,
        },
        DataType::Real32 | DataType::Real64 if text.is_empty() => types::from_text(ty, "0").ok(),
        DataType::OctetString | DataType::Domain => {
            let hex = text
                .strip_prefix("0x")
                .or_else(|| text.strip_prefix("0X"))
                .unwrap_or(text);
            types::from_text(ty, hex).ok()
        }
        DataType::TimeOfDay | DataType::TimeDifference if text.is_empty() => {
            Some(Value::Time { ms: 0, days: 0 })
        }
        _ => types::from_text(ty, text).ok(),
    }
}

/// Sub-index 0 of an array or record: the highest sub-index it has.
fn highest_sub_index(highest: u8) -> Variable {
    Variable::new(
        "Highest sub-index supported",
        DataType::Unsigned8,
        Access::Ro,
    )
    .with_value(Value::Uint(highest.into()))
}

struct Importer<'a> {
    ini: Ini<'a>,
    node_id: u8,
    findings: &'a Findings<'a>,
}

impl Importer<'_> {
    fn number<T: TryFrom<i128>>(&self, entry: &Entry, what: &str) -> Result<T, EdsError> {
        eval_number(&entry.value, self.node_id)
            .and_then(|v| T::try_from(v).ok())
            .ok_or_else(|| {
                self.ini.error(
                    entry.line,
                    format!("{what} {:?} is not a valid number", entry.value),
                )
            })
    }

    /// A sub-object from a section with DataType, AccessType and friends; an error leaves it
    /// out (no usable data type), a lesser defect is a finding and the sub-object is kept.
    fn variable(&self, section: &Section, name: String) -> Result<Variable, EdsError> {
        let dt_entry = section.get("DataType").ok_or_else(|| {
            self.ini.error(
                section.line,
                format!("[{}] has no DataType: left out", section.name),
            )
        })?;
        let code: u16 = self.number(dt_entry, "DataType")?;
        let ty = DataType::from_code(code).ok_or_else(|| {
            self.ini.error(
                dt_entry.line,
                format!(
                    "DataType 0x{code:04X} is not a CiA 301 type this file defines: [{}] left out",
                    section.name
                ),
            )
        })?;
        let access = match section.get("AccessType") {
            Some(e) => Access::parse(&e.value).unwrap_or_else(|| {
                self.findings.add(
                    e.line,
                    Severity::Error,
                    format!(
                        "AccessType {:?} is not ro/wo/rw/rwr/rww/const: read-only here",
                        e.value
                    ),
                );
                Access::Ro
            }),
            None => Access::Ro,
        };
        let mut var = Variable::new(name, ty, access);
        if let Some(e) = section.get("PDOMapping") {
            match self.number::<u8>(e, "PDOMapping") {
                Ok(v) => var.pdo_mappable = v != 0,
                Err(e) => self
                    .findings
                    .warn(e.line, format!("{}: not mappable here", e.reason)),
            }
        }
        for (key, slot) in [("LowLimit", &mut var.low), ("HighLimit", &mut var.high)] {
            if let Some(e) = section.get(key).filter(|e| !e.value.is_empty()) {
                match eval_value(ty, &e.value, self.node_id) {
                    Some(v) => *slot = Some(v),
                    // Without its limit a value the device refuses, or worse takes, could be
                    // written: the sub-object is not written at all.
                    None => {
                        self.findings.add(
                            e.line,
                            Severity::Error,
                            format!("{key} {:?} is not a valid {ty}: read-only here", e.value),
                        );
                        var.access = Access::Ro;
                    }
                }
            }
        }
        let default = section.get("DefaultValue");
        let parameter = section.get("ParameterValue");
        let empty = || eval_value(ty, "", self.node_id).unwrap_or(Value::Bytes(Vec::new()));
        let value = match parameter.or(default) {
            Some(e) => eval_value(ty, &e.value, self.node_id).unwrap_or_else(|| {
                self.findings.warn(
                    e.line,
                    format!("{} {:?} is not a valid {ty}: left empty", e.key, e.value),
                );
                empty()
            }),
            None => empty(),
        };
        var = var.with_value(value);
        var.default_text = default
            .filter(|e| eval_value(ty, &e.value, self.node_id).is_some())
            .map(|e| e.value.clone());
        var.denotation = section.get("Denotation").map(|e| e.value.clone());
        // Only a usable ParameterValue is one to configure: an unreadable one is not written.
        var.parameter_value =
            parameter.is_some_and(|e| eval_value(ty, &e.value, self.node_id).is_some());
        Ok(var)
    }

    fn object(&self, index: u16, section: &Section) -> Result<Object, EdsError> {
        let name = match section.get("ParameterName") {
            Some(e) => e.value.clone(),
            None => {
                self.findings.warn(
                    section.line,
                    format!(
                        "[{}] has no ParameterName: named {index:04X}h",
                        section.name
                    ),
                );
                format!("{index:04X}h")
            }
        };
        let code = match section.get("ObjectType") {
            Some(e) => {
                let raw: u8 = self.number(e, "ObjectType")?;
                ObjectCode::from_u8(raw).ok_or_else(|| {
                    self.ini
                        .error(e.line, format!("ObjectType {raw} is unknown: left out"))
                })?
            }
            None => ObjectCode::Var,
        };
        match code {
            ObjectCode::Var | ObjectCode::Domain | ObjectCode::Null | ObjectCode::DefType => {
                let var = self.variable(section, name.clone())?;
                let mut object = Object::var(index, var);
                object.code = if code == ObjectCode::DefType {
                    ObjectCode::DefType
                } else {
                    object.code
                };
                Ok(object)
            }
            ObjectCode::Array | ObjectCode::Record | ObjectCode::DefStruct => {
                let compact = match section.get("CompactSubObj") {
                    Some(e) => self.number::<u8>(e, "CompactSubObj")?,
                    None => 0,
                };
                let subs = if compact > 0 {
                    self.compact(index, section, &name, compact)?
                } else {
                    self.expanded(index, section)?
                };
                Ok(Object {
                    index,
                    name,
                    code,
                    subs,
                })
            }
        }
    }

    /// The sub-objects of a `CompactSubObj` array (`compact` > 0): all share the object's
    /// section.
    fn compact(
        &self,
        index: u16,
        section: &Section,
        name: &str,
        compact: u8,
    ) -> Result<BTreeMap<u8, Variable>, EdsError> {
        let mut subs = BTreeMap::new();
        let names = self.ini.section(&format!("{index:04X}Name"));
        let values = self.ini.section(&format!("{index:04X}Value"));
        for sub in 1..=compact {
            let sub_name = names
                .and_then(|s| s.get(&sub.to_string()))
                .map(|e| e.value.clone())
                .unwrap_or_else(|| format!("{name}{sub}"));
            let mut var = self.variable(section, sub_name)?;
            if let Some(e) = values.and_then(|s| s.get(&sub.to_string())) {
                match eval_value(var.data_type, &e.value, self.node_id) {
                    Some(v) => {
                        let default = var.default_text.take();
                        var = var.with_value(v);
                        var.default_text = default;
                        // A `[xxxxValue]` entry is the compact form of a ParameterValue.
                        var.parameter_value = true;
                    }
                    None => self.findings.warn(
                        e.line,
                        format!(
                            "value {:?} is not a valid {}: passed over",
                            e.value, var.data_type
                        ),
                    ),
                }
            }
            subs.insert(sub, var);
        }
        subs.insert(0, highest_sub_index(compact));
        Ok(subs)
    }

    /// The sub-objects of an array or record from their `[xxxxsubN]` sections: one that cannot
    /// be used is left out, a missing sub 0 is made (the highest sub-index found).
    fn expanded(&self, index: u16, section: &Section) -> Result<BTreeMap<u8, Variable>, EdsError> {
        let mut subs = BTreeMap::new();
        let prefix = format!("{index:04x}sub");
        for s in &self.ini.sections {
            let lower = s.name.to_ascii_lowercase();
            let Some(hex) = lower.strip_prefix(&prefix) else {
                continue;
            };
            let Ok(sub) = u8::from_str_radix(hex, 16) else {
                self.findings.add(
                    s.line,
                    Severity::Error,
                    format!("[{}] has an invalid sub-index: left out", s.name),
                );
                continue;
            };
            let sub_name = match s.get("ParameterName") {
                Some(e) => e.value.clone(),
                None => {
                    self.findings
                        .warn(s.line, format!("[{}] has no ParameterName", s.name));
                    format!("Sub-index {sub}")
                }
            };
            match self.variable(s, sub_name) {
                Ok(var) => {
                    subs.insert(sub, var);
                }
                Err(e) => self.findings.left_out(e),
            }
        }
        if let Some(e) = section.get("SubNumber") {
            match self.number::<usize>(e, "SubNumber") {
                Ok(n) if n != subs.len() => self.findings.warn(
                    e.line,
                    format!(
                        "SubNumber={n} but {} usable sub-objects found: those are taken",
                        subs.len()
                    ),
                ),
                Ok(_) => {}
                Err(e) => self.findings.warn(e.line, e.reason),
            }
        }
        let Some(&highest) = subs.keys().next_back() else {
            return Err(self.ini.error(
                section.line,
                format!("[{}] has no usable sub-object: left out", section.name),
            ));
        };
        if let std::collections::btree_map::Entry::Vacant(sub0) = subs.entry(0) {
            self.findings.warn(
                section.line,
                format!(
                    "[{}] has no sub-index 0: made, highest sub-index {highest}",
                    section.name
                ),
            );
            sub0.insert(highest_sub_index(highest));
        }
        Ok(subs)
    }

    /// The objects the lists name, with the line naming each; an entry that cannot be read is
    /// a finding and passed over.
    fn listed(&self) -> Vec<(u16, usize)> {
        let mut listed = Vec::new();
        for list in ["MandatoryObjects", "OptionalObjects", "ManufacturerObjects"] {
            let Some(section) = self.ini.section(list) else {
                continue;
            };
            let entries: Vec<&Entry> = section
                .entries
                .iter()
                .filter(|e| !e.key.eq_ignore_ascii_case("SupportedObjects"))
                .collect();
            match section
                .get("SupportedObjects")
                .map(|e| (e, self.number::<usize>(e, "SupportedObjects")))
            {
                Some((_, Ok(count))) if count == entries.len() => {}
                Some((e, Ok(count))) => self.findings.warn(
                    e.line,
                    format!(
                        "[{}] counts {count} objects and lists {}: the listed are taken",
                        section.name,
                        entries.len()
                    ),
                ),
                Some((_, Err(e))) => self.findings.warn(e.line, e.reason),
                None => self.findings.warn(
                    section.line,
                    format!("[{}] has no SupportedObjects", section.name),
                ),
            }
            for entry in entries {
                match self.number::<u16>(entry, "object index") {
                    Ok(index) => listed.push((index, entry.line)),
                    Err(e) => self
                        .findings
                        .warn(e.line, format!("{}: passed over", e.reason)),
                }
            }
        }
        listed
    }

    fn run(self) -> Result<DeviceDescription, EdsError> {
        let mut description = DeviceDescription {
            file_info: self.ini.pairs("FileInfo"),
            device_info: self.ini.pairs("DeviceInfo"),
            dummy_usage: self.ini.pairs("DummyUsage"),
            comments: self
                .ini
                .section("Comments")
                .map(|s| {
                    s.entries
                        .iter()
                        .filter(|e| !e.key.eq_ignore_ascii_case("Lines"))
                        .map(|e| e.value.clone())
                        .collect()
                })
                .unwrap_or_default(),
            ..DeviceDescription::default()
        };
        let mut indices: Vec<(u16, usize)> = self.listed();
        for s in &self.ini.sections {
            if s.name.len() == 4 {
                if let Ok(index) = u16::from_str_radix(&s.name, 16) {
                    if !indices.iter().any(|(i, _)| *i == index) {
                        indices.push((index, s.line));
                    }
                }
            }
        }
        for (index, line) in indices {
            if description.od.object(index).is_some() {
                continue;
            }
            let Some(section) = self.ini.section(&format!("{index:04X}")) else {
                self.findings.add(
                    line,
                    Severity::Error,
                    format!(
                        "object 0x{index:04X} is listed but has no [{index:04X}] section: left out"
                    ),
                );
                continue;
            };
            match self.object(index, section) {
                Ok(object) => description.od.insert(object),
                Err(e) => {
                    self.findings.left_out(e);
                    continue;
                }
            }
            if let Some(links) = self.ini.section(&format!("{index:04X}ObjectLinks")) {
                let mut linked = Vec::new();
                for e in links
                    .entries
                    .iter()
                    .filter(|e| !e.key.eq_ignore_ascii_case("ObjectLinks"))
                {
                    match self.number::<u16>(e, "object link") {
                        Ok(l) => linked.push(l),
                        Err(e) => self
                            .findings
                            .warn(e.line, format!("{}: passed over", e.reason)),
                    }
                }
                description.object_links.insert(index, linked);
            }
        }
        if description.od.objects().next().is_none() {
            return Err(self.ini.error(0, "no usable object"));
        }
        if let Some(section) = COMMISSIONING.iter().find_map(|n| self.ini.section(n)) {
            let mut c = Commissioning::default();
            for e in &section.entries {
                let bad = |e: EdsError| {
                    self.findings
                        .warn(e.line, format!("{}: passed over", e.reason))
                };
                match e.key.to_ascii_lowercase().as_str() {
                    "nodeid" => c.node_id = self.number(e, "NodeID").map_err(bad).ok(),
                    "nodename" => c.node_name = Some(e.value.clone()),
                    "baudrate" => c.baudrate = self.number(e, "Baudrate").map_err(bad).ok(),
                    _ => c.other.push((e.key.clone(), e.value.clone())),
                }
            }
            description.commissioning = Some(c);
        }
        Ok(description)
    }
}

/// Import an EDS or DCF. `node_id` resolves `$NODEID`; without it the DCF's
/// `[DeviceComissioning] NodeID` is used, else 0. `file` names the source in findings and
/// errors. Fails only when no object of the file is usable.
pub fn import(file: &str, text: &str, node_id: Option<u8>) -> Result<Imported, EdsError> {
    imported(file, text, node_id, Vec::new())
}

fn imported(
    file: &str,
    text: &str,
    node_id: Option<u8>,
    earlier: Vec<Finding>,
) -> Result<Imported, EdsError> {
    let findings = Findings {
        file,
        list: RefCell::new(earlier),
    };
    let ini = Ini::parse(file, text, &findings);
    let node_id = match node_id {
        Some(id) => id,
        None => COMMISSIONING
            .iter()
            .find_map(|n| ini.section(n))
            .and_then(|s| s.get("NodeID"))
            .and_then(|e| eval_number(&e.value, 0))
            .and_then(|v| u8::try_from(v).ok())
            .unwrap_or(0),
    };
    let description = Importer {
        ini,
        node_id,
        findings: &findings,
    }
    .run()?;
    let mut findings = findings.list.into_inner();
    findings.sort_by_key(|f| f.line);
    Ok(Imported {
        description,
        findings,
    })
}

/// Windows-1252's characters for 80h–9Fh (where it differs from ISO 8859-1; the five it leaves
/// undefined are taken as the C1 controls).
const CP1252_80: [char; 32] = [
    '€', '\u{81}', '‚', 'ƒ', '„', '…', '†', '‡', 'ˆ', '‰', 'Š', '‹', 'Œ', '\u{8d}', 'Ž', '\u{8f}',
    '\u{90}', '‘', '’', '“', '”', '•', '–', '—', '˜', '™', 'š', '›', 'œ', '\u{9d}', 'ž', 'Ÿ',
];

/// `bytes` as text: UTF-8, or else Windows-1252 (what Windows tools write), with a finding.
fn decode(file: &str, bytes: &[u8]) -> (String, Vec<Finding>) {
    match std::str::from_utf8(bytes) {
        Ok(text) => (text.to_owned(), Vec::new()),
        Err(e) => {
            let line = bytes[..e.valid_up_to()]
                .iter()
                .filter(|&&b| b == b'\n')
                .count()
                + 1;
            let text = bytes
                .iter()
                .map(|&b| match b {
                    0x80..=0x9F => CP1252_80[usize::from(b - 0x80)],
                    _ => char::from(b),
                })
                .collect();
            let finding = Finding {
                file: file.to_owned(),
                line,
                severity: Severity::Warning,
                message: "not UTF-8 (CiA 306 text is ASCII): read as Windows-1252".into(),
            };
            (text, vec![finding])
        }
    }
}

/// Import an EDS or DCF from its bytes (UTF-8, or Windows-1252 with a finding).
pub fn import_bytes(file: &str, bytes: &[u8], node_id: Option<u8>) -> Result<Imported, EdsError> {
    let (text, findings) = decode(file, bytes);
    imported(file, &text, node_id, findings)
}

/// Read and import an EDS or DCF file.
pub fn import_file(path: &std::path::Path, node_id: Option<u8>) -> Result<Imported, EdsError> {
    let name = path.display().to_string();
    let bytes = std::fs::read(path).map_err(|e| EdsError {
        file: name.clone(),
        line: 0,
        reason: e.to_string(),
    })?;
    import_bytes(&name, &bytes, node_id)
}

fn write_pairs(out: &mut String, section: &str, pairs: &[(String, String)]) {
    let _ = writeln!(out, "[{section}]");
    for (k, v) in pairs {
        let _ = writeln!(out, "{k}={v}");
    }
    out.push('\n');
}

fn write_variable(
    out: &mut String,
    section: &str,
    var: &Variable,
    code: Option<ObjectCode>,
    dcf: bool,
) {
    let _ = writeln!(out, "[{section}]");
    let _ = writeln!(out, "ParameterName={}", var.name);
    if let Some(code) = code {
        let _ = writeln!(out, "ObjectType=0x{:X}", code as u8);
    }
    let _ = writeln!(out, "DataType=0x{:04X}", var.data_type.code());
    let _ = writeln!(out, "AccessType={}", var.access.as_str());
    if let Some(default) = &var.default_text {
        let _ = writeln!(out, "DefaultValue={default}");
    }
    let _ = writeln!(out, "PDOMapping={}", u8::from(var.pdo_mappable));
    for (key, limit) in [("LowLimit", &var.low), ("HighLimit", &var.high)] {
        if let Some(v) = limit {
            let _ = writeln!(out, "{key}={}", types::to_text(var.data_type, v));
        }
    }
    if dcf {
        // Only configured values: a DCF says what a node is set to, not what could not be read.
        if let Some(bytes) = var.value_bytes().filter(|_| var.parameter_value) {
            if let Ok(v) = types::decode(var.data_type, bytes) {
                let _ = writeln!(out, "ParameterValue={}", types::to_text(var.data_type, &v));
            }
        }
        if let Some(d) = &var.denotation {
            let _ = writeln!(out, "Denotation={d}");
        }
    }
    out.push('\n');
}

/// Export as EDS text (`dcf = false`) or as DCF text with `ParameterValue`s and commissioning.
pub fn export(description: &DeviceDescription, dcf: bool) -> String {
    let mut out = String::new();
    let file_info = if description.file_info.is_empty() {
        vec![
            (
                "FileName".to_owned(),
                if dcf { "device.dcf" } else { "device.eds" }.to_owned(),
            ),
            ("FileVersion".to_owned(), "1".to_owned()),
            ("FileRevision".to_owned(), "0".to_owned()),
            ("EDSVersion".to_owned(), "4.0".to_owned()),
            ("CreatedBy".to_owned(), "canlift".to_owned()),
        ]
    } else {
        description.file_info.clone()
    };
    write_pairs(&mut out, "FileInfo", &file_info);
    if !description.device_info.is_empty() {
        write_pairs(&mut out, "DeviceInfo", &description.device_info);
    }
    if !description.dummy_usage.is_empty() {
        write_pairs(&mut out, "DummyUsage", &description.dummy_usage);
    }
    if !description.comments.is_empty() {
        let mut pairs = vec![("Lines".to_owned(), description.comments.len().to_string())];
        pairs.extend(
            description
                .comments
                .iter()
                .enumerate()
                .map(|(i, c)| (format!("Line{}", i + 1), c.clone())),
        );
        write_pairs(&mut out, "Comments", &pairs);
    }
    if dcf {
        if let Some(c) = &description.commissioning {
            let mut pairs = Vec::new();
            if let Some(id) = c.node_id {
                pairs.push(("NodeID".to_owned(), id.to_string()));
            }
            if let Some(n) = &c.node_name {
                pairs.push(("NodeName".to_owned(), n.clone()));
            }
            if let Some(b) = c.baudrate {
                pairs.push(("Baudrate".to_owned(), b.to_string()));
            }
            pairs.extend(c.other.iter().cloned());
            write_pairs(&mut out, "DeviceComissioning", &pairs);
        }
    }
    let mandatory = |i: u16| matches!(i, 0x1000 | 0x1001 | 0x1018);
    let manufacturer = |i: u16| (0x2000..0x6000).contains(&i);
    let lists: [(&str, &dyn Fn(u16) -> bool); 3] = [
        ("MandatoryObjects", &mandatory),
        ("OptionalObjects", &|i| !mandatory(i) && !manufacturer(i)),
        ("ManufacturerObjects", &manufacturer),
    ];
    for (list, belongs) in lists {
        let objects: Vec<&Object> = description
            .od
            .objects()
            .filter(|o| belongs(o.index))
            .collect();
        let mut pairs = vec![("SupportedObjects".to_owned(), objects.len().to_string())];
        pairs.extend(
            objects
                .iter()
                .enumerate()
                .map(|(i, o)| ((i + 1).to_string(), format!("0x{:04X}", o.index))),
        );
        write_pairs(&mut out, list, &pairs);
        for object in objects {
            match object.code {
                ObjectCode::Array | ObjectCode::Record | ObjectCode::DefStruct => {
                    let _ = writeln!(out, "[{:04X}]", object.index);
                    let _ = writeln!(out, "ParameterName={}", object.name);
                    let _ = writeln!(out, "ObjectType=0x{:X}", object.code as u8);
                    let _ = writeln!(out, "SubNumber={}", object.subs.len());
                    out.push('\n');
                    for (sub, var) in &object.subs {
                        write_variable(
                            &mut out,
                            &format!("{:04X}sub{sub:X}", object.index),
                            var,
                            None,
                            dcf,
                        );
                    }
                }
                _ => {
                    let var = &object.subs[&0];
                    let mut var = var.clone();
                    var.name = object.name.clone();
                    write_variable(
                        &mut out,
                        &format!("{:04X}", object.index),
                        &var,
                        Some(object.code),
                        dcf,
                    );
                }
            }
            if let Some(links) = description.object_links.get(&object.index) {
                let mut pairs = vec![("ObjectLinks".to_owned(), links.len().to_string())];
                pairs.extend(
                    links
                        .iter()
                        .enumerate()
                        .map(|(i, l)| ((i + 1).to_string(), format!("0x{l:04X}"))),
                );
                write_pairs(
                    &mut out,
                    &format!("{:04X}ObjectLinks", object.index),
                    &pairs,
                );
            }
        }
    }
    out
}

impl DeviceDescription {
    /// The `DefaultValue` text of a VAR as written in the file.
    pub fn variable_default(&self, index: u16) -> Option<&str> {
        self.od.variable(index, 0).ok()?.default_text.as_deref()
    }
}

impl fmt::Display for DeviceDescription {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&export(self, false))
    }
}

#[cfg(test)]
mod tests;
