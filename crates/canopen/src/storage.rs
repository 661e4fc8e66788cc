//! Store and restore parameters (CiA 301 §7.5.2.13–14): 0x1010 "store parameters" takes the
//! signature "save", 0x1011 "restore default parameters" the signature "load". Sub-index 1 means
//! all parameters, 2 communication (0x1000–0x1FFF), 3 application (0x6000–0x9FFF), 4
//! manufacturer-specific (0x2000–0x5FFF).
//!
//! Stored are the values of writable variables and of those marked
//! [`crate::od::Variable::persist`], in a small text file (`INDEX:SUB HEX` per line) written
//! atomically: a temporary file, fsync, rename over the old one, fsync of the directory. A
//! restore removes the group's values from the file; the defaults return at the next reset.

use std::fmt::Write as _;
use std::io::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::od::{Access, Object, ObjectCode, ObjectDictionary, Variable, VariableHook, WriteGuard};
use crate::sdo::abort::AbortCode;
use crate::types::{DataType, Value};

/// The "save" signature (ASCII, little-endian).
pub const SAVE: u32 = u32::from_le_bytes(*b"save");
/// The "load" signature.
pub const LOAD: u32 = u32::from_le_bytes(*b"load");

const HEADER: &str = "# canlift stored parameters v1";

/// The index ranges of storage sub-index `sub` (1–4).
pub fn group(sub: u8) -> Option<&'static [std::ops::RangeInclusive<u16>]> {
    const ALL: &[std::ops::RangeInclusive<u16>] = &[0x1000..=0xFFFF];
    const COMMUNICATION: &[std::ops::RangeInclusive<u16>] = &[0x1000..=0x1FFF];
    const APPLICATION: &[std::ops::RangeInclusive<u16>] = &[0x6000..=0x9FFF];
    const MANUFACTURER: &[std::ops::RangeInclusive<u16>] = &[0x2000..=0x5FFF];
    match sub {
        1 => Some(ALL),
        2 => Some(COMMUNICATION),
        3 => Some(APPLICATION),
        4 => Some(MANUFACTURER),
        _ => None,
    }
}

/// One stored value.
pub type Entry = (u16, u8, Vec<u8>);

/// Why a storage file could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum StorageError {
    /// The file could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A line is not `INDEX:SUB HEX`.
    #[error("{path}:{line}: {reason}")]
    Format {
        /// The file.
        path: String,
        /// 1-based line.
        line: usize,
        /// What is wrong.
        reason: String,
    },
}

/// The values `sub`'s group keeps, from `od`.
pub fn snapshot(od: &ObjectDictionary, sub: u8) -> Vec<Entry> {
    let Some(ranges) = group(sub) else {
        return Vec::new();
    };
    let mut out = Vec::new();
    for object in od
        .objects()
        .filter(|o| ranges.iter().any(|r| r.contains(&o.index)))
    {
        if matches!(object.index, 0x1010 | 0x1011) {
            continue;
        }
        for (s, var) in &object.subs {
            if !(var.access.writable() || var.persist) {
                continue;
            }
            if let Some(bytes) = var.value_bytes() {
                out.push((object.index, *s, bytes.to_vec()));
            }
        }
    }
    out
}

/// The text of a storage file.
pub fn encode(entries: &[Entry]) -> String {
    let mut text = format!("{HEADER}\n");
    for (index, sub, bytes) in entries {
        let _ = write!(text, "{index:04X}:{sub:02X} ");
        for b in bytes {
            let _ = write!(text, "{b:02X}");
        }
        text.push('\n');
    }
    text
}

/// Parse a storage file's text; `path` names it in errors.
pub fn decode(path: &str, text: &str) -> Result<Vec<Entry>, StorageError> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let bad = |reason: &str| StorageError::Format {
            path: path.to_owned(),
            line: n + 1,
            reason: reason.to_owned(),
        };
        let (mux, hex) = line.split_once(' ').unwrap_or((line, ""));
        let (index, sub) = mux
            .split_once(':')
            .ok_or_else(|| bad("expected INDEX:SUB"))?;
        let index = u16::from_str_radix(index, 16).map_err(|_| bad("invalid index"))?;
        let sub = u8::from_str_radix(sub, 16).map_err(|_| bad("invalid sub-index"))?;
        let bytes = match crate::types::from_text(DataType::Domain, hex) {
            Ok(Value::Bytes(b)) => b,
            _ => return Err(bad("invalid hex data")),
        };
        out.push((index, sub, bytes));
    }
    Ok(out)
}

/// Read a storage file; a missing file is an empty one.
pub fn load(path: &Path) -> Result<Vec<Entry>, StorageError> {
    match std::fs::read_to_string(path) {
        Ok(text) => decode(&path.display().to_string(), &text),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(source) => Err(StorageError::Io {
            path: path.display().to_string(),
            source,
        }),
    }
}

/// Write `text` to `path` atomically: temporary file, fsync, rename, fsync of the directory.
pub fn write_atomically(path: &Path, text: &str) -> std::io::Result<()> {
    write_file(path, text, false)
}

/// [`write_atomically`] for a secret (a cloud token, an API key, a password): the file is
/// readable by its owner alone from the moment it is created, never for an instant by others.
pub fn write_private_atomically(path: &Path, text: &str) -> std::io::Result<()> {
    write_file(path, text, true)
}

/// Write `text` to a new file — `private`: of mode 0600 on Unix, else as the umask says —
/// fsynced, then renamed over `path`.
fn write_file(path: &Path, text: &str, private: bool) -> std::io::Result<()> {
    let dir = path
        .parent()
        .filter(|d| !d.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir)?;
    let tmp = dir.join(format!(
        ".{}.tmp",
        path.file_name()
            .and_then(|n| n.to_str())
            .unwrap_or("storage")
    ));
    {
        let mut options = std::fs::OpenOptions::new();
        options.write(true).create(true).truncate(true);
        #[cfg(unix)]
        if private {
            std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
        }
        let file = options.open(&tmp)?;
        // A temporary file left by a crash keeps its mode: a private one is set anew.
        #[cfg(unix)]
        if private {
            file.set_permissions(std::os::unix::fs::PermissionsExt::from_mode(0o600))?;
        }
        #[cfg(not(unix))]
        let _ = private;
        let mut file = file;
        file.write_all(text.as_bytes())?;
        file.sync_all()?;
    }
    std::fs::rename(&tmp, path)?;
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
    Ok(())
}

/// Put stored values into `od` (owner-side); values for objects that no longer exist or no
/// longer fit are skipped with a log line.
pub fn apply(od: &mut ObjectDictionary, entries: &[Entry]) {
    for (index, sub, bytes) in entries {
        if let Err(code) = od.set(*index, *sub, bytes) {
            tracing::warn!(index, sub, %code, "stored value not restored");
        }
    }
}

/// 0x1010/0x1011 sub-indices read as 1: "the device saves/restores on command".
struct Capability;

impl VariableHook for Capability {
    fn on_read(&self, _: u16, _: u8, _: &[u8]) -> Result<Option<Vec<u8>>, AbortCode> {
        Ok(Some(1u32.to_le_bytes().to_vec()))
    }
}

/// Performs store and restore when 0x1010/0x1011 are written, so failures reach the SDO client
/// as abort 0x08000020.
pub struct StorageGuard {
    path: PathBuf,
}

/// Replace the values of `fresh` in the file at `path`, keeping every other stored value.
fn merge(path: &Path, fresh: Vec<Entry>) -> Result<(), StorageError> {
    let mut kept = load(path)?;
    kept.retain(|(i, s, _)| !fresh.iter().any(|(fi, fs, _)| fi == i && fs == s));
    kept.extend(fresh);
    kept.sort_by_key(|(i, s, _)| (*i, *s));
    write_atomically(path, &encode(&kept)).map_err(|source| StorageError::Io {
        path: path.display().to_string(),
        source,
    })
}

/// Store the read-only persistent values (counters such as a trip counter) of `od` into the
/// file at `path` without touching stored parameters: a device keeps its counters in
/// non-volatile memory by itself, while parameters are kept only by "store parameters".
pub fn store_counters(od: &ObjectDictionary, path: &Path) -> Result<(), StorageError> {
    let counters = od
        .objects()
        .flat_map(|o| o.subs.iter().map(move |(s, v)| (o.index, *s, v)))
        .filter(|(_, _, v)| v.persist && !v.access.writable())
        .filter_map(|(i, s, v)| v.value_bytes().map(|b| (i, s, b.to_vec())))
        .collect();
    merge(path, counters)
}

impl StorageGuard {
    fn store(&self, od: &ObjectDictionary, sub: u8) -> Result<(), AbortCode> {
        merge(&self.path, snapshot(od, sub)).map_err(|e| {
            tracing::error!(error = %e, "storing parameters failed");
            AbortCode::CANNOT_STORE
        })
    }

    fn restore_defaults(&self, sub: u8) -> Result<(), AbortCode> {
        let ranges = group(sub).ok_or(AbortCode::NO_SUB_INDEX)?;
        let mut kept = load(&self.path).map_err(|_| AbortCode::CANNOT_STORE)?;
        kept.retain(|(i, _, _)| !ranges.iter().any(|r| r.contains(i)));
        write_atomically(&self.path, &encode(&kept)).map_err(|_| AbortCode::CANNOT_STORE)
    }
}

impl WriteGuard for StorageGuard {
    fn check(
        &self,
        od: &ObjectDictionary,
        index: u16,
        sub: u8,
        data: &[u8],
    ) -> Result<(), AbortCode> {
        if !matches!(index, 0x1010 | 0x1011) || sub == 0 {
            return Ok(());
        }
        let signature =
            u32::from_le_bytes(data.try_into().map_err(|_| AbortCode::LENGTH_MISMATCH)?);
        match (index, signature) {
            (0x1010, SAVE) => self.store(od, sub),
            (0x1011, LOAD) => self.restore_defaults(sub),
            _ => Err(AbortCode::CANNOT_STORE),
        }
    }
}

/// Add 0x1010 and 0x1011 (sub-indices 1–4) and the guard that stores into `path`.
pub fn add_storage_objects(od: &mut ObjectDictionary, path: PathBuf) {
    let names = [
        "all parameters",
        "communication parameters",
        "application parameters",
        "manufacturer parameters",
    ];
    for (index, verb) in [(0x1010u16, "Save"), (0x1011, "Restore default")] {
        let entries = names.iter().enumerate().map(|(i, name)| {
            let var = Variable::new(format!("{verb} {name}"), DataType::Unsigned32, Access::Rw)
                .with_value(Value::Uint(1))
                .with_hook(Arc::new(Capability));
            (i as u8 + 1, var)
        });
        let title = if index == 0x1010 {
            "Store parameters"
        } else {
            "Restore default parameters"
        };
        od.insert(Object::composite(index, title, ObjectCode::Array, entries));
    }
    od.guard(Arc::new(StorageGuard { path }));
}

#[cfg(test)]
mod tests {
    use super::*;

    fn dictionary(path: &Path) -> ObjectDictionary {
        let mut od = ObjectDictionary::new();
        od.insert(Object::var(
            0x1017,
            Variable::new("Heartbeat", DataType::Unsigned16, Access::Rw),
        ));
        od.insert(Object::var(
            0x2000,
            Variable::new("Trips", DataType::Unsigned32, Access::Ro).persistent(),
        ));
        od.insert(Object::var(
            0x2001,
            Variable::new("Name", DataType::VisibleString, Access::Rw),
        ));
        od.insert(Object::var(
            0x2002,
            Variable::new("Live", DataType::Unsigned32, Access::Ro),
        ));
        od.insert(Object::var(
            0x6000,
            Variable::new("Setpoint", DataType::Integer16, Access::Rw),
        ));
        add_storage_objects(&mut od, path.to_path_buf());
        od
    }

    #[test]
    fn save_restart_restore() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("node.params");
        let mut od = dictionary(&path);
        od.set(0x1017, 0, &500u16.to_le_bytes()).unwrap();
        od.set(0x2000, 0, &42u32.to_le_bytes()).unwrap();
        od.set(0x2001, 0, b"car 1").unwrap();
        od.set(0x2002, 0, &7u32.to_le_bytes()).unwrap();
        od.set(0x6000, 0, &(-5i16).to_le_bytes()).unwrap();
        assert_eq!(
            od.read(0x1010, 1).unwrap(),
            1u32.to_le_bytes(),
            "capability, not the signature"
        );
        assert_eq!(od.write(0x1010, 1, b"sav!"), Err(AbortCode::CANNOT_STORE));
        od.write(0x1010, 1, b"save").unwrap();
        assert_eq!(od.read(0x1010, 1).unwrap(), 1u32.to_le_bytes());

        // A restart: fresh defaults, then the stored values.
        let mut fresh = dictionary(&path);
        apply(&mut fresh, &load(&path).unwrap());
        assert_eq!(fresh.get_value(0x1017, 0).unwrap(), Value::Uint(500));
        assert_eq!(
            fresh.get_value(0x2000, 0).unwrap(),
            Value::Uint(42),
            "persistent counter"
        );
        assert_eq!(
            fresh.get_value(0x2001, 0).unwrap(),
            Value::Text("car 1".into())
        );
        assert_eq!(
            fresh.get_value(0x2002, 0).unwrap(),
            Value::Uint(0),
            "live values are not kept"
        );
        assert_eq!(fresh.get_value(0x6000, 0).unwrap(), Value::Int(-5));

        // Restore defaults of the communication group only.
        fresh.write(0x1011, 2, b"load").unwrap();
        let mut again = dictionary(&path);
        apply(&mut again, &load(&path).unwrap());
        assert_eq!(again.get_value(0x1017, 0).unwrap(), Value::Uint(0));
        assert_eq!(again.get_value(0x2000, 0).unwrap(), Value::Uint(42));
        // Storing the application group alone leaves the others untouched.
        again.set(0x6000, 0, &9i16.to_le_bytes()).unwrap();
        again.set(0x2000, 0, &43u32.to_le_bytes()).unwrap();
        again.write(0x1010, 3, b"save").unwrap();
        let entries = load(&path).unwrap();
        assert!(entries.contains(&(0x6000, 0, 9i16.to_le_bytes().to_vec())));
        assert!(
            entries.contains(&(0x2000, 0, 42u32.to_le_bytes().to_vec())),
            "group 4 not re-stored"
        );
        assert!(
            !dir.path().join(".node.params.tmp").exists(),
            "no temporary file left"
        );
    }

    #[test]
    fn corrupt_files_name_the_line() {
        let err = decode("x.params", "# header\n1017:00 F401\n1017 zz\n").unwrap_err();
        assert_eq!(err.to_string(), "x.params:3: expected INDEX:SUB");
        let err = decode("x.params", "2000:00 F4Z1\n").unwrap_err();
        assert!(err.to_string().contains(":1: invalid hex data"), "{err}");
        let entries = vec![(0x1017, 0, vec![0xF4, 0x01]), (0x2001, 0, vec![])];
        assert_eq!(decode("x", &encode(&entries)).unwrap(), entries);
    }
}
