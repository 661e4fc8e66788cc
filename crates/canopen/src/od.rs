//! The object dictionary (CiA 301 §7.4): objects by 16-bit index, each with sub-objects by
//! 8-bit sub-index, typed, with access rights, limits, application hooks and change watchers.
//!
//! Every access that comes from the network goes through [`ObjectDictionary::read`] /
//! [`ObjectDictionary::write`] (or the streaming [`ObjectDictionary::open_read`] /
//! [`ObjectDictionary::open_write`] the SDO server uses), which enforce access, length and limits
//! with the CiA 301 abort codes. The application itself uses [`ObjectDictionary::set`], which
//! skips the access check (a read-only counter is still written by its owner).

use std::collections::BTreeMap;
use std::fmt;
use std::sync::Arc;

use crate::sdo::abort::AbortCode;
use crate::types::{self, DataType, Value};

/// Object code (CiA 301 table 42).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum ObjectCode {
    /// No data fields.
    Null = 0,
    /// Large variable amount of data.
    Domain = 2,
    /// A type definition.
    DefType = 5,
    /// A record type definition.
    DefStruct = 6,
    /// A single value.
    Var = 7,
    /// Sub-objects of one type; sub-index 0 holds the count.
    Array = 8,
    /// Sub-objects of different types; sub-index 0 holds the highest sub-index.
    Record = 9,
}

impl ObjectCode {
    /// The code with numeric value `v`.
    pub fn from_u8(v: u8) -> Option<Self> {
        use ObjectCode::*;
        [Null, Domain, DefType, DefStruct, Var, Array, Record]
            .into_iter()
            .find(|c| *c as u8 == v)
    }
}

/// Access attribute of a sub-object (CiA 306 `AccessType`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Access {
    /// Read only.
    Ro,
    /// Write only.
    Wo,
    /// Read and write.
    Rw,
    /// Read and write; mapped into TPDOs (process input).
    Rwr,
    /// Read and write; mapped into RPDOs (process output).
    Rww,
    /// Read only, never changes.
    Const,
}

impl Access {
    /// Whether SDO reads are allowed.
    pub fn readable(self) -> bool {
        !matches!(self, Access::Wo)
    }

    /// Whether SDO writes are allowed.
    pub fn writable(self) -> bool {
        matches!(self, Access::Wo | Access::Rw | Access::Rwr | Access::Rww)
    }

    /// The CiA 306 spelling.
    pub fn as_str(self) -> &'static str {
        match self {
            Access::Ro => "ro",
            Access::Wo => "wo",
            Access::Rw => "rw",
            Access::Rwr => "rwr",
            Access::Rww => "rww",
            Access::Const => "const",
        }
    }

    /// Parse the CiA 306 spelling (case-insensitive).
    pub fn parse(text: &str) -> Option<Self> {
        Some(match text.trim().to_ascii_lowercase().as_str() {
            "ro" => Access::Ro,
            "wo" => Access::Wo,
            "rw" => Access::Rw,
            "rwr" => Access::Rwr,
            "rww" => Access::Rww,
            "const" => Access::Const,
            _ => return None,
        })
    }
}

/// Application logic attached to a sub-object: produce a value when it is read, accept or
/// refuse a value when it is written (and act on it).
pub trait VariableHook: Send + Sync {
    /// Called on every read; `Ok(Some(bytes))` replaces the stored value.
    fn on_read(&self, _index: u16, _sub: u8, _stored: &[u8]) -> Result<Option<Vec<u8>>, AbortCode> {
        Ok(None)
    }

    /// Called before a written value is stored; an error refuses the write with that code.
    fn on_write(&self, _index: u16, _sub: u8, _data: &[u8]) -> Result<(), AbortCode> {
        Ok(())
    }
}

/// A DOMAIN whose content lives outside the dictionary (a file, a log, firmware) and is streamed
/// by the SDO server chunk by chunk instead of being held in memory.
pub trait DomainStream: Send + Sync {
    /// Total size if known (sent as the SDO size indication).
    fn size(&self) -> Option<u64>;
    /// Fill `buf` from `offset`; `Ok(0)` at the end.
    fn read_at(&self, offset: u64, buf: &mut [u8]) -> Result<usize, AbortCode>;
    /// A download begins; `size` as indicated by the client.
    fn begin_write(&self, size: Option<u64>) -> Result<(), AbortCode>;
    /// The next chunk of a download at `offset`.
    fn write_chunk(&self, offset: u64, data: &[u8]) -> Result<(), AbortCode>;
    /// The download is complete with `total` bytes.
    fn end_write(&self, total: u64) -> Result<(), AbortCode>;
}

#[derive(Clone)]
enum Storage {
    Value(Vec<u8>),
    Stream(Arc<dyn DomainStream>),
}

/// One sub-object: a typed value with its attributes.
#[derive(Clone)]
pub struct Variable {
    /// Parameter name.
    pub name: String,
    /// Data type.
    pub data_type: DataType,
    /// Access attribute.
    pub access: Access,
    /// Whether it may be mapped into a PDO.
    pub pdo_mappable: bool,
    /// The default value as written in an EDS (may contain `$NODEID`).
    pub default_text: Option<String>,
    /// Lowest value a write may set.
    pub low: Option<Value>,
    /// Highest value a write may set.
    pub high: Option<Value>,
    /// Longest value a write may set, for strings and domains (bytes).
    pub max_len: Option<usize>,
    /// DCF `Denotation`.
    pub denotation: Option<String>,
    /// The value is a DCF `ParameterValue`: configured for this node, what `dcf apply` writes.
    pub parameter_value: bool,
    /// Kept by "store parameters" (0x1010) although not writable over the network, e.g. a trip
    /// counter that must survive restarts. Writable variables are always kept.
    pub persist: bool,
    storage: Storage,
    hook: Option<Arc<dyn VariableHook>>,
}

impl fmt::Debug for Variable {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Variable")
            .field("name", &self.name)
            .field("data_type", &self.data_type)
            .field("access", &self.access)
            .field("pdo_mappable", &self.pdo_mappable)
            .field("default_text", &self.default_text)
            .field("low", &self.low)
            .field("high", &self.high)
            .field("value", &self.value_bytes())
            .finish()
    }
}

/// Equality of definitions and stored values (hooks and streams are not compared).
impl PartialEq for Variable {
    fn eq(&self, o: &Self) -> bool {
        self.name == o.name
            && self.data_type == o.data_type
            && self.access == o.access
            && self.pdo_mappable == o.pdo_mappable
            && self.default_text == o.default_text
            && self.low == o.low
            && self.high == o.high
            && self.denotation == o.denotation
            && self.value_bytes() == o.value_bytes()
    }
}

impl Variable {
    /// A variable of `data_type` with `access`, holding the type's zero value.
    pub fn new(name: impl Into<String>, data_type: DataType, access: Access) -> Self {
        Variable {
            name: name.into(),
            data_type,
            access,
            pdo_mappable: false,
            default_text: None,
            low: None,
            high: None,
            max_len: None,
            denotation: None,
            parameter_value: false,
            persist: false,
            storage: Storage::Value(vec![0; data_type.size().unwrap_or(0)]),
            hook: None,
        }
    }

    /// With an initial value (also recorded as its default).
    pub fn with_value(mut self, value: Value) -> Self {
        if let Ok(bytes) = types::encode(self.data_type, &value) {
            self.default_text = Some(types::to_text(self.data_type, &value));
            self.storage = Storage::Value(bytes);
        }
        self
    }

    /// With limits for writes.
    pub fn with_limits(mut self, low: Option<Value>, high: Option<Value>) -> Self {
        self.low = low;
        self.high = high;
        self
    }

    /// Mappable into PDOs.
    pub fn mappable(mut self) -> Self {
        self.pdo_mappable = true;
        self
    }

    /// Kept by "store parameters" even though read-only (counters and the like).
    pub fn persistent(mut self) -> Self {
        self.persist = true;
        self
    }

    /// With an application hook.
    pub fn with_hook(mut self, hook: Arc<dyn VariableHook>) -> Self {
        self.hook = Some(hook);
        self
    }

    /// A DOMAIN served from `stream`.
    pub fn with_stream(mut self, stream: Arc<dyn DomainStream>) -> Self {
        self.storage = Storage::Stream(stream);
        self
    }

    /// The stored bytes (`None` for a streamed DOMAIN).
    pub fn value_bytes(&self) -> Option<&[u8]> {
        match &self.storage {
            Storage::Value(v) => Some(v),
            Storage::Stream(_) => None,
        }
    }

    /// Check `data` against type size, maximum length and limits.
    fn check(&self, data: &[u8]) -> Result<(), AbortCode> {
        if let Some(size) = self.data_type.size() {
            if data.len() > size {
                return Err(AbortCode::LENGTH_TOO_HIGH);
            }
            if data.len() < size {
                return Err(AbortCode::LENGTH_TOO_LOW);
            }
        } else if self.max_len.is_some_and(|max| data.len() > max) {
            return Err(AbortCode::LENGTH_TOO_HIGH);
        }
        if self.low.is_none() && self.high.is_none() && self.data_type != DataType::Boolean {
            return Ok(());
        }
        let value = types::decode(self.data_type, data).map_err(|e| e.abort_code())?;
        let below = |limit: &Value| compare(&value, limit).is_some_and(|o| o.is_lt());
        let above = |limit: &Value| compare(&value, limit).is_some_and(|o| o.is_gt());
        if self.low.as_ref().is_some_and(below) {
            return Err(AbortCode::VALUE_TOO_LOW);
        }
        if self.high.as_ref().is_some_and(above) {
            return Err(AbortCode::VALUE_TOO_HIGH);
        }
        Ok(())
    }
}

/// Order two numeric values of possibly different representation.
pub fn compare(a: &Value, b: &Value) -> Option<std::cmp::Ordering> {
    match (a, b) {
        (Value::Int(x), Value::Int(y)) => Some(x.cmp(y)),
        (Value::Uint(x), Value::Uint(y)) => Some(x.cmp(y)),
        (Value::Int(x), Value::Uint(y)) => Some(i128::from(*x).cmp(&i128::from(*y))),
        (Value::Uint(x), Value::Int(y)) => Some(i128::from(*x).cmp(&i128::from(*y))),
        _ => a.as_f64()?.partial_cmp(&b.as_f64()?),
    }
}

/// One object: a VAR (sub-index 0 only), an ARRAY or RECORD (sub-index 0 = highest sub-index),
/// or a DOMAIN.
#[derive(Debug, Clone, PartialEq)]
pub struct Object {
    /// Index.
    pub index: u16,
    /// Parameter name.
    pub name: String,
    /// Object code.
    pub code: ObjectCode,
    /// Sub-objects by sub-index.
    pub subs: BTreeMap<u8, Variable>,
}

impl Object {
    /// A VAR (or DOMAIN, by data type) with its single value at sub-index 0.
    pub fn var(index: u16, var: Variable) -> Self {
        let code = if var.data_type == DataType::Domain {
            ObjectCode::Domain
        } else {
            ObjectCode::Var
        };
        Object {
            index,
            name: var.name.clone(),
            code,
            subs: BTreeMap::from([(0, var)]),
        }
    }

    /// An ARRAY or RECORD with sub-index 0 set to the highest sub-index of `entries`.
    pub fn composite(
        index: u16,
        name: impl Into<String>,
        code: ObjectCode,
        entries: impl IntoIterator<Item = (u8, Variable)>,
    ) -> Self {
        let mut subs: BTreeMap<u8, Variable> = entries.into_iter().collect();
        let highest = subs.keys().next_back().copied().unwrap_or(0);
        subs.entry(0).or_insert_with(|| {
            Variable::new(
                "Highest sub-index supported",
                DataType::Unsigned8,
                Access::Ro,
            )
            .with_value(Value::Uint(highest.into()))
        });
        Object {
            index,
            name: name.into(),
            code,
            subs,
        }
    }
}

/// A dictionary shared between the protocol tasks and the application.
pub type SharedDictionary = Arc<std::sync::Mutex<ObjectDictionary>>;

/// Called with (index, sub-index) after every successful write or set.
pub type Watcher = Arc<dyn Fn(u16, u8) + Send + Sync>;

/// A rule over several objects that network writes must satisfy (e.g. the PDO mapping
/// procedure of CiA 301 §7.5.2.35–38). It sees the whole dictionary before a value is stored.
pub trait WriteGuard: Send + Sync {
    /// Refuse the write of `data` to `index`/`sub` with an abort code, or allow it.
    fn check(
        &self,
        od: &ObjectDictionary,
        index: u16,
        sub: u8,
        data: &[u8],
    ) -> Result<(), AbortCode>;
}

/// Largest DOMAIN a download may buffer in memory (bigger ones need a [`DomainStream`]).
pub const MAX_BUFFERED_DOMAIN: usize = 16 << 20;

/// The object dictionary of one node.
#[derive(Clone, Default)]
pub struct ObjectDictionary {
    objects: BTreeMap<u16, Object>,
    watchers: Vec<Watcher>,
    guards: Vec<Arc<dyn WriteGuard>>,
}

impl fmt::Debug for ObjectDictionary {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_map().entries(self.objects.iter()).finish()
    }
}

/// Dictionaries are equal when they define the same objects with the same values.
impl PartialEq for ObjectDictionary {
    fn eq(&self, other: &Self) -> bool {
        self.objects == other.objects
    }
}

/// Streaming access to a value, for SDO uploads.
pub enum Reader {
    /// The value, read at once.
    Buffer {
        /// The bytes.
        data: Vec<u8>,
        /// Bytes taken so far.
        pos: usize,
    },
    /// A [`DomainStream`].
    Stream {
        /// The stream.
        stream: Arc<dyn DomainStream>,
        /// Bytes taken so far.
        offset: u64,
    },
}

impl Reader {
    /// Total size if known.
    pub fn size(&self) -> Option<u64> {
        match self {
            Reader::Buffer { data, .. } => Some(data.len() as u64),
            Reader::Stream { stream, .. } => stream.size(),
        }
    }

    /// Fill `buf` with the next bytes; returns how many (0 at the end).
    pub fn read(&mut self, buf: &mut [u8]) -> Result<usize, AbortCode> {
        match self {
            Reader::Buffer { data, pos } => {
                let n = buf.len().min(data.len() - *pos);
                buf[..n].copy_from_slice(&data[*pos..*pos + n]);
                *pos += n;
                Ok(n)
            }
            Reader::Stream { stream, offset } => {
                let n = stream.read_at(*offset, buf)?;
                *offset += n as u64;
                Ok(n)
            }
        }
    }
}

/// Streaming access to a value, for SDO downloads; nothing is stored before [`Writer::finish`]
/// (streams receive chunks as they come).
pub struct Writer {
    index: u16,
    sub: u8,
    written: u64,
    sink: Sink,
}

enum Sink {
    Buffer(Vec<u8>, usize),
    Stream(Arc<dyn DomainStream>),
}

impl Writer {
    /// Take the next chunk.
    pub fn write(&mut self, data: &[u8]) -> Result<(), AbortCode> {
        match &mut self.sink {
            Sink::Buffer(buf, limit) => {
                if buf.len() + data.len() > *limit {
                    return Err(if *limit >= MAX_BUFFERED_DOMAIN {
                        AbortCode::OUT_OF_MEMORY
                    } else {
                        AbortCode::LENGTH_TOO_HIGH
                    });
                }
                buf.extend_from_slice(data);
            }
            Sink::Stream(stream) => stream.write_chunk(self.written, data)?,
        }
        self.written += data.len() as u64;
        Ok(())
    }

    /// Bytes taken so far.
    pub fn written(&self) -> u64 {
        self.written
    }

    /// Complete the download: check and store the value, or close the stream.
    pub fn finish(self, od: &mut ObjectDictionary) -> Result<(), AbortCode> {
        match self.sink {
            Sink::Buffer(buf, _) => od.write(self.index, self.sub, &buf),
            Sink::Stream(stream) => {
                stream.end_write(self.written)?;
                od.notify(self.index, self.sub);
                Ok(())
            }
        }
    }
}

impl ObjectDictionary {
    /// An empty dictionary.
    pub fn new() -> Self {
        Self::default()
    }

    /// Add or replace an object.
    pub fn insert(&mut self, object: Object) {
        self.objects.insert(object.index, object);
    }

    /// Remove an object.
    pub fn remove(&mut self, index: u16) -> Option<Object> {
        self.objects.remove(&index)
    }

    /// The object at `index`.
    pub fn object(&self, index: u16) -> Option<&Object> {
        self.objects.get(&index)
    }

    /// The object at `index`, mutable (definitions, not values: use [`Self::set`] for those).
    pub fn object_mut(&mut self, index: u16) -> Option<&mut Object> {
        self.objects.get_mut(&index)
    }

    /// Make the values `index`'s sub-objects hold now their defaults: what a device sets up at
    /// boot is what its description gives (CiA 306 `DefaultValue`).
    pub fn keep_as_defaults(&mut self, index: u16) {
        let Some(object) = self.objects.get_mut(&index) else {
            return;
        };
        for var in object.subs.values_mut() {
            let value = var
                .value_bytes()
                .and_then(|bytes| types::decode(var.data_type, bytes).ok());
            if let Some(value) = value {
                var.default_text = Some(types::to_text(var.data_type, &value));
            }
        }
    }

    /// All objects in index order.
    pub fn objects(&self) -> impl Iterator<Item = &Object> {
        self.objects.values()
    }

    /// The sub-object at `index`/`sub`, or the abort code a client would get.
    pub fn variable(&self, index: u16, sub: u8) -> Result<&Variable, AbortCode> {
        let object = self.objects.get(&index).ok_or(AbortCode::NO_OBJECT)?;
        object.subs.get(&sub).ok_or(AbortCode::NO_SUB_INDEX)
    }

    fn variable_mut(&mut self, index: u16, sub: u8) -> Result<&mut Variable, AbortCode> {
        let object = self.objects.get_mut(&index).ok_or(AbortCode::NO_OBJECT)?;
        object.subs.get_mut(&sub).ok_or(AbortCode::NO_SUB_INDEX)
    }

    /// Be told of every change (successful writes and sets). Watchers run synchronously while
    /// the dictionary is borrowed: they should hand the news on (e.g. into a channel), not
    /// access the dictionary.
    pub fn watch(&mut self, watcher: Watcher) {
        self.watchers.push(watcher);
    }

    /// Add a rule that every network write must pass.
    pub fn guard(&mut self, guard: Arc<dyn WriteGuard>) {
        self.guards.push(guard);
    }

    fn notify(&self, index: u16, sub: u8) {
        for w in &self.watchers {
            w(index, sub);
        }
    }

    /// Read as a network client would (access checked, hooks run).
    pub fn read(&self, index: u16, sub: u8) -> Result<Vec<u8>, AbortCode> {
        let mut reader = self.open_read(index, sub)?;
        match reader {
            Reader::Buffer { data, .. } => Ok(data),
            Reader::Stream { .. } => {
                let mut out = Vec::new();
                let mut chunk = [0u8; 4096];
                loop {
                    let n = reader.read(&mut chunk)?;
                    if n == 0 {
                        return Ok(out);
                    }
                    if out.len() + n > MAX_BUFFERED_DOMAIN {
                        return Err(AbortCode::OUT_OF_MEMORY);
                    }
                    out.extend_from_slice(&chunk[..n]);
                }
            }
        }
    }

    /// Start reading a value as a network client would.
    pub fn open_read(&self, index: u16, sub: u8) -> Result<Reader, AbortCode> {
        let var = self.variable(index, sub)?;
        if !var.access.readable() {
            return Err(AbortCode::WRITE_ONLY);
        }
        match &var.storage {
            Storage::Stream(stream) => Ok(Reader::Stream {
                stream: stream.clone(),
                offset: 0,
            }),
            Storage::Value(stored) => {
                let produced = match &var.hook {
                    Some(hook) => hook.on_read(index, sub, stored)?,
                    None => None,
                };
                Ok(Reader::Buffer {
                    data: produced.unwrap_or_else(|| stored.clone()),
                    pos: 0,
                })
            }
        }
    }

    /// Start writing a value as a network client would; `size` is the client's indication.
    pub fn open_write(&self, index: u16, sub: u8, size: Option<u64>) -> Result<Writer, AbortCode> {
        let var = self.variable(index, sub)?;
        if !var.access.writable() {
            return Err(AbortCode::READ_ONLY);
        }
        let limit = var
            .data_type
            .size()
            .or(var.max_len)
            .unwrap_or(MAX_BUFFERED_DOMAIN);
        let sink = match &var.storage {
            Storage::Stream(stream) => {
                stream.begin_write(size)?;
                Sink::Stream(stream.clone())
            }
            Storage::Value(_) => {
                if let Some(size) = size {
                    if size > limit as u64 {
                        return Err(if limit >= MAX_BUFFERED_DOMAIN {
                            AbortCode::OUT_OF_MEMORY
                        } else {
                            AbortCode::LENGTH_TOO_HIGH
                        });
                    }
                    if var.data_type.size().is_some_and(|s| (size as usize) < s) {
                        return Err(AbortCode::LENGTH_TOO_LOW);
                    }
                }
                Sink::Buffer(
                    Vec::with_capacity(size.unwrap_or(0).min(limit as u64) as usize),
                    limit,
                )
            }
        };
        Ok(Writer {
            index,
            sub,
            written: 0,
            sink,
        })
    }

    /// Write as a network client would: access, length and limits checked, hook consulted,
    /// watchers told.
    pub fn write(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<(), AbortCode> {
        let object_code = self.object(index).map(|o| o.code);
        let var = self.variable(index, sub)?;
        if !var.access.writable() {
            return Err(AbortCode::READ_ONLY);
        }
        var.check(data)?;
        if sub == 0 && object_code == Some(ObjectCode::Array) {
            // The count of an ARRAY cannot exceed the sub-objects that exist.
            let highest = self
                .object(index)
                .and_then(|o| o.subs.keys().next_back().copied())
                .unwrap_or(0);
            if data.first().is_some_and(|&n| n > highest) {
                return Err(AbortCode::VALUE_TOO_HIGH);
            }
        }
        for guard in &self.guards {
            guard.check(self, index, sub, data)?;
        }
        if let Some(hook) = &var.hook {
            hook.on_write(index, sub, data)?;
        }
        self.store(index, sub, data)
    }

    /// Set a value as its owner: no access check (a read-only counter is still updated by the
    /// application), but the type's length must fit. Watchers are told.
    pub fn set(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<(), AbortCode> {
        let var = self.variable(index, sub)?;
        if var.data_type.size().is_some_and(|s| s != data.len()) {
            return Err(AbortCode::LENGTH_MISMATCH);
        }
        self.store(index, sub, data)
    }

    fn store(&mut self, index: u16, sub: u8, data: &[u8]) -> Result<(), AbortCode> {
        let var = self.variable_mut(index, sub)?;
        match &mut var.storage {
            Storage::Value(v) => {
                v.clear();
                v.extend_from_slice(data);
            }
            Storage::Stream(_) => return Err(AbortCode::UNSUPPORTED_ACCESS),
        }
        self.notify(index, sub);
        Ok(())
    }

    /// The value at `index`/`sub` if it is an unsigned integer that fits 32 bits (COB-IDs,
    /// times, counts of the communication profile); owner's view like [`Self::get_value`].
    pub fn get_u32(&self, index: u16, sub: u8) -> Option<u32> {
        match self.get_value(index, sub) {
            Ok(Value::Uint(v)) => u32::try_from(v).ok(),
            _ => None,
        }
    }

    /// The decoded value at `index`/`sub` (owner's view: no access check, no hook).
    pub fn get_value(&self, index: u16, sub: u8) -> Result<Value, AbortCode> {
        let var = self.variable(index, sub)?;
        let bytes = var.value_bytes().ok_or(AbortCode::UNSUPPORTED_ACCESS)?;
        types::decode(var.data_type, bytes).map_err(|e| e.abort_code())
    }

    /// Set a decoded value as its owner.
    pub fn set_value(&mut self, index: u16, sub: u8, value: &Value) -> Result<(), AbortCode> {
        let ty = self.variable(index, sub)?.data_type;
        let bytes = types::encode(ty, value).map_err(|e| e.abort_code())?;
        self.set(index, sub, &bytes)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    fn sample() -> ObjectDictionary {
        let mut od = ObjectDictionary::new();
        od.insert(Object::var(
            0x1000,
            Variable::new("Device type", DataType::Unsigned32, Access::Ro)
                .with_value(Value::Uint(0x0001_01A1)),
        ));
        od.insert(Object::var(
            0x1017,
            Variable::new("Producer heartbeat time", DataType::Unsigned16, Access::Rw)
                .with_limits(Some(Value::Uint(10)), Some(Value::Uint(60_000))),
        ));
        od.insert(Object::var(
            0x1F50,
            Variable::new("Program", DataType::Domain, Access::Wo),
        ));
        od.insert(Object::composite(
            0x1016,
            "Consumer heartbeat time",
            ObjectCode::Array,
            (1..=4).map(|i| {
                (
                    i,
                    Variable::new(format!("Consumer {i}"), DataType::Unsigned32, Access::Rw),
                )
            }),
        ));
        od.object_mut(0x1016)
            .unwrap()
            .subs
            .get_mut(&0)
            .unwrap()
            .access = Access::Rw;
        od
    }

    #[test]
    fn reads_and_writes_enforce_the_rules() {
        let mut od = sample();
        assert_eq!(od.read(0x1000, 0).unwrap(), 0x0001_01A1u32.to_le_bytes());
        assert_eq!(od.read(0x2000, 0), Err(AbortCode::NO_OBJECT));
        assert_eq!(od.read(0x1000, 1), Err(AbortCode::NO_SUB_INDEX));
        assert_eq!(od.read(0x1F50, 0), Err(AbortCode::WRITE_ONLY));
        assert_eq!(od.write(0x1000, 0, &[0; 4]), Err(AbortCode::READ_ONLY));
        assert_eq!(
            od.write(0x1017, 0, &[1, 2, 3]),
            Err(AbortCode::LENGTH_TOO_HIGH)
        );
        assert_eq!(od.write(0x1017, 0, &[1]), Err(AbortCode::LENGTH_TOO_LOW));
        assert_eq!(
            od.write(0x1017, 0, &5u16.to_le_bytes()),
            Err(AbortCode::VALUE_TOO_LOW)
        );
        assert_eq!(
            od.write(0x1017, 0, &60_001u16.to_le_bytes()),
            Err(AbortCode::VALUE_TOO_HIGH)
        );
        od.write(0x1017, 0, &1000u16.to_le_bytes()).unwrap();
        assert_eq!(od.get_value(0x1017, 0).unwrap(), Value::Uint(1000));
        assert_eq!(
            od.object(0x1016).unwrap().subs[&0].value_bytes(),
            Some(&[4u8][..])
        );
        assert_eq!(od.write(0x1016, 0, &[5]), Err(AbortCode::VALUE_TOO_HIGH));
        od.write(0x1016, 0, &[2]).unwrap();
        od.set(0x1000, 0, &7u32.to_le_bytes()).unwrap();
        assert_eq!(od.set(0x1000, 0, &[7]), Err(AbortCode::LENGTH_MISMATCH));
    }

    #[test]
    fn hooks_produce_and_veto_and_watchers_hear_changes() {
        struct Counter;
        impl VariableHook for Counter {
            fn on_read(&self, _: u16, _: u8, _: &[u8]) -> Result<Option<Vec<u8>>, AbortCode> {
                Ok(Some(42u32.to_le_bytes().to_vec()))
            }
            fn on_write(&self, _: u16, _: u8, data: &[u8]) -> Result<(), AbortCode> {
                if data == [0, 0, 0, 0] {
                    Err(AbortCode::DEVICE_STATE)
                } else {
                    Ok(())
                }
            }
        }
        let mut od = sample();
        od.insert(Object::var(
            0x2000,
            Variable::new("Live", DataType::Unsigned32, Access::Rw).with_hook(Arc::new(Counter)),
        ));
        let seen = Arc::new(Mutex::new(Vec::new()));
        let log = seen.clone();
        od.watch(Arc::new(move |i, s| log.lock().unwrap().push((i, s))));
        assert_eq!(od.read(0x2000, 0).unwrap(), 42u32.to_le_bytes());
        assert_eq!(od.write(0x2000, 0, &[0; 4]), Err(AbortCode::DEVICE_STATE));
        od.write(0x2000, 0, &[1, 0, 0, 0]).unwrap();
        od.set(0x1000, 0, &[0; 4]).unwrap();
        assert_eq!(*seen.lock().unwrap(), vec![(0x2000, 0), (0x1000, 0)]);
    }

    #[test]
    fn streamed_domains() {
        struct Blob(Mutex<Vec<u8>>);
        impl DomainStream for Blob {
            fn size(&self) -> Option<u64> {
                Some(self.0.lock().unwrap().len() as u64)
            }
            fn read_at(&self, offset: u64, buf: &mut [u8]) -> Result<usize, AbortCode> {
                let data = self.0.lock().unwrap();
                let start = (offset as usize).min(data.len());
                let n = buf.len().min(data.len() - start);
                buf[..n].copy_from_slice(&data[start..start + n]);
                Ok(n)
            }
            fn begin_write(&self, _: Option<u64>) -> Result<(), AbortCode> {
                self.0.lock().unwrap().clear();
                Ok(())
            }
            fn write_chunk(&self, _: u64, data: &[u8]) -> Result<(), AbortCode> {
                self.0.lock().unwrap().extend_from_slice(data);
                Ok(())
            }
            fn end_write(&self, _: u64) -> Result<(), AbortCode> {
                Ok(())
            }
        }
        let mut od = ObjectDictionary::new();
        let blob = Arc::new(Blob(Mutex::new(Vec::new())));
        od.insert(Object::var(
            0x2100,
            Variable::new("Log", DataType::Domain, Access::Rw).with_stream(blob.clone()),
        ));
        let mut w = od.open_write(0x2100, 0, Some(10_000)).unwrap();
        for chunk in vec![7u8; 10_000].chunks(7) {
            w.write(chunk).unwrap();
        }
        w.finish(&mut od).unwrap();
        assert_eq!(od.read(0x2100, 0).unwrap(), vec![7u8; 10_000]);
        assert_eq!(od.open_read(0x2100, 0).unwrap().size(), Some(10_000));
    }

    #[test]
    fn buffered_domains_are_bounded() {
        let od = sample();
        assert!(matches!(
            od.open_write(0x1F50, 0, Some(u64::MAX)),
            Err(AbortCode::OUT_OF_MEMORY)
        ));
        assert!(matches!(
            od.open_write(0x1017, 0, Some(3)),
            Err(AbortCode::LENGTH_TOO_HIGH)
        ));
    }
}
