//! CiA 306 electronic data sheets (EDS) and device configuration files (DCF): import into an
//! [`ObjectDictionary`] and export back.
//!
//! Import accepts what tools write in practice: keys and section names in any case, `;` comments,
//! decimal, `0x` hex and leading-zero octal numbers, `$NODEID` formulas in either order
//! (`$NODEID+0x180`, `0x180 + $NODEID`), `CompactSubObj` arrays with their `[xxxxName]` and
//! `[xxxxValue]` sections, `ObjectLinks`, `DummyUsage`, the `DeviceComissioning` section under
//! its common spellings, and DCF `ParameterValue` / `Denotation`. Every error names the file, the
//! line and the reason. Export writes the expanded form (one section per sub-object), so
//! import → export → import gives the same dictionary.

use std::collections::{BTreeMap, HashMap};
use std::fmt::{self, Write as _};

use crate::od::{Access, Object, ObjectCode, ObjectDictionary, Variable};
use crate::types::{self, DataType, Value};

/// Why a file could not be imported.
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

struct Ini<'a> {
    file: &'a str,
    sections: Vec<Section>,
    by_name: HashMap<String, usize>,
}

impl<'a> Ini<'a> {
    fn parse(file: &'a str, text: &str) -> Result<Self, EdsError> {
        let mut ini = Ini {
            file,
            sections: Vec::new(),
            by_name: HashMap::new(),
        };
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        for (n, raw) in text.lines().enumerate() {
            let line = n + 1;
            let trimmed = raw.trim();
            if trimmed.is_empty() || trimmed.starts_with(';') || trimmed.starts_with('#') {
                continue;
            }
            if let Some(rest) = trimmed.strip_prefix('[') {
                let name = rest
                    .strip_suffix(']')
                    .ok_or_else(|| ini.error(line, "section header without closing ']'"))?
                    .trim();
                let key = name.to_ascii_lowercase();
                if ini.by_name.contains_key(&key) {
                    return Err(ini.error(line, format!("section [{name}] appears twice")));
                }
                ini.by_name.insert(key, ini.sections.len());
                ini.sections.push(Section {
                    name: name.to_owned(),
                    line,
                    entries: Vec::new(),
                });
                continue;
            }
            let Some((key, value)) = trimmed.split_once('=') else {
                return Err(ini.error(line, format!("expected KEY=VALUE, found {trimmed:?}")));
            };
            let Some(section) = ini.sections.last_mut() else {
                return Err(ini.error(line, "entry before the first [section]"));
            };
            let key = key.trim();
            if section.get(key).is_some() {
                return Err(EdsError {
                    file: file.to_owned(),
                    line,
                    reason: format!("key {key} appears twice in [{}]", section.name),
                });
            }
            section.entries.push(Entry {
                key: key.to_owned(),
                value: value.trim().to_owned(),
                line,
            });
        }
        Ok(ini)
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

struct Importer<'a> {
    ini: Ini<'a>,
    node_id: u8,
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

    fn required<'s>(&self, section: &'s Section, key: &str) -> Result<&'s Entry, EdsError> {
        section.get(key).ok_or_else(|| {
            self.ini
                .error(section.line, format!("[{}] has no {key}", section.name))
        })
    }

    /// A sub-object from a section with DataType, AccessType and friends; `defaults` supplies
    /// the attributes a CompactSubObj array shares.
    fn variable(&self, section: &Section, name: String) -> Result<Variable, EdsError> {
        let dt_entry = self.required(section, "DataType")?;
        let code: u16 = self.number(dt_entry, "DataType")?;
        let ty = DataType::from_code(code).ok_or_else(|| {
            self.ini.error(
                dt_entry.line,
                format!("DataType 0x{code:04X} is not a CiA 301 type"),
            )
        })?;
        let access = match section.get("AccessType") {
            Some(e) => Access::parse(&e.value).ok_or_else(|| {
                self.ini.error(
                    e.line,
                    format!("AccessType {:?} is not ro/wo/rw/rwr/rww/const", e.value),
                )
            })?,
            None => Access::Ro,
        };
        let mut var = Variable::new(name, ty, access);
        if let Some(e) = section.get("PDOMapping") {
            var.pdo_mappable = self.number::<u8>(e, "PDOMapping")? != 0;
        }
        for (key, slot) in [("LowLimit", &mut var.low), ("HighLimit", &mut var.high)] {
            if let Some(e) = section.get(key).filter(|e| !e.value.is_empty()) {
                *slot = Some(eval_value(ty, &e.value, self.node_id).ok_or_else(|| {
                    self.ini
                        .error(e.line, format!("{key} {:?} is not a valid {ty}", e.value))
                })?);
            }
        }
        let default = section.get("DefaultValue");
        let parameter = section.get("ParameterValue");
        let initial = parameter.or(default);
        let value = match initial {
            Some(e) => eval_value(ty, &e.value, self.node_id).ok_or_else(|| {
                self.ini.error(
                    e.line,
                    format!("{} {:?} is not a valid {ty}", e.key, e.value),
                )
            })?,
            None => eval_value(ty, "", self.node_id).unwrap_or(Value::Bytes(Vec::new())),
        };
        var = var.with_value(value);
        var.default_text = default.map(|e| e.value.clone());
        var.denotation = section.get("Denotation").map(|e| e.value.clone());
        var.parameter_value = parameter.is_some();
        Ok(var)
    }

    fn object(&self, index: u16, section: &Section) -> Result<Object, EdsError> {
        let name = self.required(section, "ParameterName")?.value.clone();
        let code = match section.get("ObjectType") {
            Some(e) => {
                let raw: u8 = self.number(e, "ObjectType")?;
                ObjectCode::from_u8(raw).ok_or_else(|| {
                    self.ini
                        .error(e.line, format!("ObjectType {raw} is unknown"))
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
                let mut subs = BTreeMap::new();
                if compact > 0 {
                    let names = self.ini.section(&format!("{index:04X}Name"));
                    let values = self.ini.section(&format!("{index:04X}Value"));
                    for sub in 1..=compact {
                        let sub_name = names
                            .and_then(|s| s.get(&sub.to_string()))
                            .map(|e| e.value.clone())
                            .unwrap_or_else(|| format!("{name}{sub}"));
                        let mut var = self.variable(section, sub_name)?;
                        if let Some(e) = values.and_then(|s| s.get(&sub.to_string())) {
                            let v = eval_value(var.data_type, &e.value, self.node_id).ok_or_else(
                                || {
                                    self.ini.error(
                                        e.line,
                                        format!(
                                            "value {:?} is not a valid {}",
                                            e.value, var.data_type
                                        ),
                                    )
                                },
                            )?;
                            let default = var.default_text.take();
                            var = var.with_value(v);
                            var.default_text = default;
                            // A `[xxxxValue]` entry is the compact form of a ParameterValue.
                            var.parameter_value = true;
                        }
                        subs.insert(sub, var);
                    }
                    let count = Variable::new(
                        "Highest sub-index supported",
                        DataType::Unsigned8,
                        Access::Ro,
                    )
                    .with_value(Value::Uint(compact.into()));
                    subs.insert(0, count);
                } else {
                    let prefix = format!("{index:04x}sub");
                    for s in &self.ini.sections {
                        let lower = s.name.to_ascii_lowercase();
                        let Some(hex) = lower.strip_prefix(&prefix) else {
                            continue;
                        };
                        let sub = u8::from_str_radix(hex, 16).map_err(|_| {
                            self.ini
                                .error(s.line, format!("[{}] has an invalid sub-index", s.name))
                        })?;
                        let sub_name = self.required(s, "ParameterName")?.value.clone();
                        subs.insert(sub, self.variable(s, sub_name)?);
                    }
                    if let Some(e) = section.get("SubNumber") {
                        let n: usize = self.number(e, "SubNumber")?;
                        if n != subs.len() {
                            return Err(self.ini.error(
                                e.line,
                                format!(
                                    "SubNumber={n} but {} sub-object sections found",
                                    subs.len()
                                ),
                            ));
                        }
                    }
                }
                Ok(Object {
                    index,
                    name,
                    code,
                    subs,
                })
            }
        }
    }

    fn listed(&self) -> Result<Vec<(u16, usize)>, EdsError> {
        let mut listed = Vec::new();
        for list in ["MandatoryObjects", "OptionalObjects", "ManufacturerObjects"] {
            let Some(section) = self.ini.section(list) else {
                continue;
            };
            let count: usize = match section.get("SupportedObjects") {
                Some(e) => self.number(e, "SupportedObjects")?,
                None => 0,
            };
            for i in 1..=count {
                let entry = section.get(&i.to_string()).ok_or_else(|| {
                    self.ini.error(
                        section.line,
                        format!(
                            "[{}] lists {count} objects but has no entry {i}",
                            section.name
                        ),
                    )
                })?;
                listed.push((self.number::<u16>(entry, "object index")?, entry.line));
            }
        }
        Ok(listed)
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
        let mut indices: Vec<(u16, usize)> = self.listed()?;
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
            let section = self.ini.section(&format!("{index:04X}")).ok_or_else(|| {
                self.ini.error(
                    line,
                    format!("object 0x{index:04X} is listed but has no [{index:04X}] section"),
                )
            })?;
            description.od.insert(self.object(index, section)?);
            if let Some(links) = self.ini.section(&format!("{index:04X}ObjectLinks")) {
                let mut linked = Vec::new();
                for e in links
                    .entries
                    .iter()
                    .filter(|e| !e.key.eq_ignore_ascii_case("ObjectLinks"))
                {
                    linked.push(self.number::<u16>(e, "object link")?);
                }
                description.object_links.insert(index, linked);
            }
        }
        if let Some(section) = COMMISSIONING.iter().find_map(|n| self.ini.section(n)) {
            let mut c = Commissioning::default();
            for e in &section.entries {
                match e.key.to_ascii_lowercase().as_str() {
                    "nodeid" => c.node_id = Some(self.number(e, "NodeID")?),
                    "nodename" => c.node_name = Some(e.value.clone()),
                    "baudrate" => c.baudrate = Some(self.number(e, "Baudrate")?),
                    _ => c.other.push((e.key.clone(), e.value.clone())),
                }
            }
            description.commissioning = Some(c);
        }
        Ok(description)
    }
}

/// Import an EDS or DCF. `node_id` resolves `$NODEID`; without it the DCF's
/// `[DeviceComissioning] NodeID` is used, else 0. `file` names the source in errors.
pub fn import(file: &str, text: &str, node_id: Option<u8>) -> Result<DeviceDescription, EdsError> {
    let ini = Ini::parse(file, text)?;
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
    Importer { ini, node_id }.run()
}

/// Read and import an EDS or DCF file.
pub fn import_file(
    path: &std::path::Path,
    node_id: Option<u8>,
) -> Result<DeviceDescription, EdsError> {
    let name = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|e| EdsError {
        file: name.clone(),
        line: 0,
        reason: e.to_string(),
    })?;
    import(&name, &text, node_id)
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
