//! CiA 301 data types (§7.1): the static types of table 44 with their little-endian wire
//! encoding, value ranges, and the text form the NXg connector carries (docs/PROTOCOL.md §Values).
//!
//! Text form: integers in decimal, BOOLEAN `0`/`1`, reals as the shortest decimal that reads back
//! to the same value, VISIBLE_STRING and UNICODE_STRING as text, OCTET_STRING and DOMAIN as hex
//! digit pairs, TIME_OF_DAY as `YYYY-MM-DDTHH:MM:SS.mmm` (CANopen epoch 1984-01-01),
//! TIME_DIFFERENCE as a number of milliseconds.

use std::fmt;

use crate::sdo::abort::AbortCode;

/// A CiA 301 static data type, with its object dictionary index (table 44) as discriminant.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
#[repr(u16)]
#[allow(missing_docs)]
pub enum DataType {
    Boolean = 0x0001,
    Integer8 = 0x0002,
    Integer16 = 0x0003,
    Integer32 = 0x0004,
    Unsigned8 = 0x0005,
    Unsigned16 = 0x0006,
    Unsigned32 = 0x0007,
    Real32 = 0x0008,
    VisibleString = 0x0009,
    OctetString = 0x000A,
    UnicodeString = 0x000B,
    TimeOfDay = 0x000C,
    TimeDifference = 0x000D,
    Domain = 0x000F,
    Integer24 = 0x0010,
    Real64 = 0x0011,
    Integer40 = 0x0012,
    Integer48 = 0x0013,
    Integer56 = 0x0014,
    Integer64 = 0x0015,
    Unsigned24 = 0x0016,
    Unsigned40 = 0x0018,
    Unsigned48 = 0x0019,
    Unsigned56 = 0x001A,
    Unsigned64 = 0x001B,
}

/// Every data type, in index order.
pub const ALL_TYPES: [DataType; 25] = {
    use DataType::*;
    [
        Boolean,
        Integer8,
        Integer16,
        Integer32,
        Unsigned8,
        Unsigned16,
        Unsigned32,
        Real32,
        VisibleString,
        OctetString,
        UnicodeString,
        TimeOfDay,
        TimeDifference,
        Domain,
        Integer24,
        Real64,
        Integer40,
        Integer48,
        Integer56,
        Integer64,
        Unsigned24,
        Unsigned40,
        Unsigned48,
        Unsigned56,
        Unsigned64,
    ]
};

impl DataType {
    /// The type with object dictionary index `code`.
    pub fn from_code(code: u16) -> Option<Self> {
        ALL_TYPES.iter().copied().find(|t| t.code() == code)
    }

    /// The object dictionary index of the type (as in EDS `DataType=`).
    pub fn code(self) -> u16 {
        self as u16
    }

    /// The specification's name (`UNSIGNED32`).
    pub fn name(self) -> &'static str {
        use DataType::*;
        match self {
            Boolean => "BOOLEAN",
            Integer8 => "INTEGER8",
            Integer16 => "INTEGER16",
            Integer24 => "INTEGER24",
            Integer32 => "INTEGER32",
            Integer40 => "INTEGER40",
            Integer48 => "INTEGER48",
            Integer56 => "INTEGER56",
            Integer64 => "INTEGER64",
            Unsigned8 => "UNSIGNED8",
            Unsigned16 => "UNSIGNED16",
            Unsigned24 => "UNSIGNED24",
            Unsigned32 => "UNSIGNED32",
            Unsigned40 => "UNSIGNED40",
            Unsigned48 => "UNSIGNED48",
            Unsigned56 => "UNSIGNED56",
            Unsigned64 => "UNSIGNED64",
            Real32 => "REAL32",
            Real64 => "REAL64",
            VisibleString => "VISIBLE_STRING",
            OctetString => "OCTET_STRING",
            UnicodeString => "UNICODE_STRING",
            TimeOfDay => "TIME_OF_DAY",
            TimeDifference => "TIME_DIFFERENCE",
            Domain => "DOMAIN",
        }
    }

    /// The type named `name` (case-insensitive), as written in specifications and tools.
    pub fn from_name(name: &str) -> Option<Self> {
        ALL_TYPES
            .iter()
            .copied()
            .find(|t| t.name().eq_ignore_ascii_case(name))
    }

    /// Size on the wire in bytes for fixed-size types; `None` for strings and DOMAIN.
    pub fn size(self) -> Option<usize> {
        use DataType::*;
        Some(match self {
            Boolean | Integer8 | Unsigned8 => 1,
            Integer16 | Unsigned16 => 2,
            Integer24 | Unsigned24 => 3,
            Integer32 | Unsigned32 | Real32 => 4,
            Integer40 | Unsigned40 => 5,
            Integer48 | Unsigned48 | TimeOfDay | TimeDifference => 6,
            Integer56 | Unsigned56 => 7,
            Integer64 | Unsigned64 | Real64 => 8,
            VisibleString | OctetString | UnicodeString | Domain => return None,
        })
    }

    /// Whether values are signed integers.
    pub fn is_signed(self) -> bool {
        use DataType::*;
        matches!(
            self,
            Integer8
                | Integer16
                | Integer24
                | Integer32
                | Integer40
                | Integer48
                | Integer56
                | Integer64
        )
    }

    /// Whether values are unsigned integers.
    pub fn is_unsigned(self) -> bool {
        use DataType::*;
        matches!(
            self,
            Unsigned8
                | Unsigned16
                | Unsigned24
                | Unsigned32
                | Unsigned40
                | Unsigned48
                | Unsigned56
                | Unsigned64
        )
    }

    /// Whether the type is numeric (integers and reals; BOOLEAN counts as an integer 0/1).
    pub fn is_numeric(self) -> bool {
        self.is_signed()
            || self.is_unsigned()
            || matches!(
                self,
                DataType::Real32 | DataType::Real64 | DataType::Boolean
            )
    }

    /// The inclusive range of an integer type (BOOLEAN: 0..=1).
    pub fn integer_range(self) -> Option<(i128, i128)> {
        let bits = self.size()? as u32 * 8;
        if self.is_signed() {
            Some((-(1i128 << (bits - 1)), (1i128 << (bits - 1)) - 1))
        } else if self.is_unsigned() {
            Some((0, (1i128 << bits) - 1))
        } else if self == DataType::Boolean {
            Some((0, 1))
        } else {
            None
        }
    }
}

impl fmt::Display for DataType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// A decoded value of some [`DataType`].
#[derive(Debug, Clone, PartialEq)]
pub enum Value {
    /// BOOLEAN.
    Bool(bool),
    /// Any signed integer type.
    Int(i64),
    /// Any unsigned integer type.
    Uint(u64),
    /// REAL32.
    Real32(f32),
    /// REAL64.
    Real64(f64),
    /// VISIBLE_STRING or UNICODE_STRING.
    Text(String),
    /// OCTET_STRING or DOMAIN.
    Bytes(Vec<u8>),
    /// TIME_OF_DAY or TIME_DIFFERENCE: milliseconds (after midnight) and days.
    Time {
        /// Milliseconds, 28 bits.
        ms: u32,
        /// Days.
        days: u16,
    },
}

impl Value {
    /// The value as a real number, for numeric types and BOOLEAN (0/1); `None` otherwise.
    pub fn as_f64(&self) -> Option<f64> {
        Some(match self {
            Value::Bool(b) => f64::from(u8::from(*b)),
            Value::Int(i) => *i as f64,
            Value::Uint(u) => *u as f64,
            Value::Real32(f) => f64::from(*f),
            Value::Real64(f) => *f,
            _ => return None,
        })
    }
}

/// Why a value does not fit its type.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum TypeError {
    /// The byte length differs from the type's size.
    #[error("{ty} takes {expected} bytes, not {got}")]
    Length {
        /// The type.
        ty: DataType,
        /// Its size.
        expected: usize,
        /// What was given.
        got: usize,
    },
    /// The value is not of this type.
    #[error("{value} is not a valid {ty}")]
    Invalid {
        /// The type.
        ty: DataType,
        /// The offending value or text.
        value: String,
    },
    /// A number above the type's range.
    #[error("{value} is too high for {ty}")]
    TooHigh {
        /// The type.
        ty: DataType,
        /// The offending text.
        value: String,
    },
    /// A number below the type's range.
    #[error("{value} is too low for {ty}")]
    TooLow {
        /// The type.
        ty: DataType,
        /// The offending text.
        value: String,
    },
}

impl TypeError {
    /// The SDO abort code that reports this error on the wire.
    pub fn abort_code(&self) -> AbortCode {
        match self {
            TypeError::Length { expected, got, .. } if got > expected => AbortCode::LENGTH_TOO_HIGH,
            TypeError::Length { .. } => AbortCode::LENGTH_TOO_LOW,
            TypeError::Invalid { .. } => AbortCode::INVALID_VALUE,
            TypeError::TooHigh { .. } => AbortCode::VALUE_TOO_HIGH,
            TypeError::TooLow { .. } => AbortCode::VALUE_TOO_LOW,
        }
    }
}

fn invalid(ty: DataType, value: impl fmt::Display) -> TypeError {
    TypeError::Invalid {
        ty,
        value: value.to_string(),
    }
}

/// Encode `value` as `ty` on the wire (little-endian, CiA 301 §7.1.4).
pub fn encode(ty: DataType, value: &Value) -> Result<Vec<u8>, TypeError> {
    use DataType::*;
    let size = ty.size();
    let fits = |v: i128| {
        let (lo, hi) = ty.integer_range().unwrap_or((0, 0));
        (lo..=hi).contains(&v)
    };
    match (ty, value) {
        (Boolean, Value::Bool(b)) => Ok(vec![u8::from(*b)]),
        (Boolean, Value::Uint(v @ 0..=1)) => Ok(vec![*v as u8]),
        (Boolean, Value::Int(v @ 0..=1)) => Ok(vec![*v as u8]),
        (_, Value::Int(v)) if ty.is_signed() || ty.is_unsigned() => {
            if !fits(i128::from(*v)) {
                return Err(invalid(ty, v));
            }
            Ok(v.to_le_bytes()[..size.unwrap_or(8)].to_vec())
        }
        (_, Value::Uint(v)) if ty.is_signed() || ty.is_unsigned() => {
            if !fits(i128::from(*v)) {
                return Err(invalid(ty, v));
            }
            Ok(v.to_le_bytes()[..size.unwrap_or(8)].to_vec())
        }
        (Real32, Value::Real32(v)) => Ok(v.to_le_bytes().to_vec()),
        (Real64, Value::Real64(v)) => Ok(v.to_le_bytes().to_vec()),
        (Real64, Value::Real32(v)) => Ok(f64::from(*v).to_le_bytes().to_vec()),
        (VisibleString, Value::Text(s)) => {
            if s.chars()
                .any(|c| !(c == ' ' || c.is_ascii_graphic() || c as u32 >= 0xA0) || c as u32 > 0xFF)
            {
                return Err(invalid(ty, s));
            }
            // ISO 8859-1: every char below 0x100 is one byte.
            Ok(s.chars().map(|c| c as u8).collect())
        }
        // A NUL would end the string for every reader (and for [`decode`]).
        (UnicodeString, Value::Text(s)) if s.contains('\0') => Err(invalid(ty, s)),
        (UnicodeString, Value::Text(s)) => {
            Ok(s.encode_utf16().flat_map(u16::to_le_bytes).collect())
        }
        (OctetString | Domain, Value::Bytes(b)) => Ok(b.clone()),
        (TimeOfDay | TimeDifference, Value::Time { ms, days }) if *ms < 1 << 28 => {
            let mut out = ms.to_le_bytes().to_vec();
            out.extend(days.to_le_bytes());
            Ok(out)
        }
        _ => Err(invalid(ty, format!("{value:?}"))),
    }
}

/// Decode `bytes` as `ty`.
pub fn decode(ty: DataType, bytes: &[u8]) -> Result<Value, TypeError> {
    use DataType::*;
    if let Some(size) = ty.size() {
        if bytes.len() != size {
            return Err(TypeError::Length {
                ty,
                expected: size,
                got: bytes.len(),
            });
        }
    }
    let mut wide = [0u8; 8];
    let n = bytes.len().min(8);
    wide[..n].copy_from_slice(&bytes[..n]);
    Ok(match ty {
        Boolean => match bytes[0] {
            0 => Value::Bool(false),
            1 => Value::Bool(true),
            other => return Err(invalid(ty, other)),
        },
        _ if ty.is_unsigned() => Value::Uint(u64::from_le_bytes(wide)),
        _ if ty.is_signed() => {
            let shift = 64 - 8 * bytes.len() as u32;
            Value::Int(i64::from_le_bytes(wide) << shift >> shift)
        }
        Real32 => Value::Real32(f32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]])),
        Real64 => Value::Real64(f64::from_le_bytes(wide)),
        // Strings end at the first NUL where a device pads them (CiA 301 allows both).
        VisibleString => {
            let end = bytes.iter().position(|&b| b == 0).unwrap_or(bytes.len());
            Value::Text(bytes[..end].iter().map(|&b| char::from(b)).collect())
        }
        UnicodeString => {
            if !bytes.len().is_multiple_of(2) {
                return Err(invalid(ty, "odd byte count"));
            }
            let units: Vec<u16> = bytes
                .chunks(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]))
                .take_while(|&u| u != 0)
                .collect();
            Value::Text(String::from_utf16(&units).map_err(|_| invalid(ty, "invalid UTF-16"))?)
        }
        OctetString | Domain => Value::Bytes(bytes.to_vec()),
        TimeOfDay | TimeDifference => Value::Time {
            ms: u32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) & 0x0FFF_FFFF,
            days: u16::from_le_bytes([bytes[4], bytes[5]]),
        },
        _ => unreachable!("every type is covered above"),
    })
}

/// Days from 1970-01-01 to the CANopen epoch 1984-01-01.
pub const CANOPEN_EPOCH_DAYS: i64 = 5113;

/// Civil date (year, month, day) of `days` after 1970-01-01 (Howard Hinnant's algorithm).
pub fn civil_from_days(days: i64) -> (i64, u32, u32) {
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let month = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    (yoe + era * 400 + i64::from(month <= 2), month, day)
}

/// Days after 1970-01-01 of a civil date.
pub fn days_from_civil(year: i64, month: u32, day: u32) -> i64 {
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y.rem_euclid(400);
    let mp = i64::from((month + 9) % 12);
    let doy = (153 * mp + 2) / 5 + i64::from(day) - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    era * 146_097 + doe - 719_468
}

/// The text form of `value` (see the module documentation).
pub fn to_text(ty: DataType, value: &Value) -> String {
    match value {
        Value::Bool(b) => u8::from(*b).to_string(),
        Value::Int(v) => v.to_string(),
        Value::Uint(v) => v.to_string(),
        Value::Real32(v) => shortest_real(format!("{v:?}")),
        Value::Real64(v) => shortest_real(format!("{v:?}")),
        Value::Text(s) => s.clone(),
        Value::Bytes(b) => b.iter().map(|x| format!("{x:02X}")).collect(),
        Value::Time { ms, days } if ty == DataType::TimeOfDay => {
            let (y, m, d) = civil_from_days(CANOPEN_EPOCH_DAYS + i64::from(*days));
            let (h, min, s, milli) = (ms / 3_600_000, ms / 60_000 % 60, ms / 1000 % 60, ms % 1000);
            format!("{y:04}-{m:02}-{d:02}T{h:02}:{min:02}:{s:02}.{milli:03}")
        }
        Value::Time { ms, days } => (u64::from(*days) * 86_400_000 + u64::from(*ms)).to_string(),
    }
}

/// `Debug` prints the shortest digits that read back exactly, switching to exponent notation for
/// very large and small magnitudes; only its `.0` on whole numbers is dropped.
fn shortest_real(debug: String) -> String {
    match debug.strip_suffix(".0") {
        Some(whole) => whole.to_owned(),
        None => debug,
    }
}

fn parse_hex_bytes(ty: DataType, text: &str) -> Result<Vec<u8>, TypeError> {
    let text: String = text.chars().filter(|c| !c.is_ascii_whitespace()).collect();
    if !text.len().is_multiple_of(2) || !text.bytes().all(|b| b.is_ascii_hexdigit()) {
        return Err(invalid(ty, text));
    }
    Ok((0..text.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&text[i..i + 2], 16).unwrap_or(0))
        .collect())
}

/// Parse an integer in the text form of values: decimal (leading zeros are decimal: `010` is
/// ten) or `0x` hex, with an optional sign.
pub fn parse_text_integer(text: &str) -> Option<i128> {
    let t = text.trim();
    let (neg, digits) = match t.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, t.strip_prefix('+').unwrap_or(t)),
    };
    let magnitude = match digits
        .strip_prefix("0x")
        .or_else(|| digits.strip_prefix("0X"))
    {
        Some(hex) if !hex.is_empty() && hex.bytes().all(|b| b.is_ascii_hexdigit()) => {
            i128::from_str_radix(hex, 16).ok()?
        }
        Some(_) => return None,
        None if !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit()) => {
            digits.parse::<i128>().ok()?
        }
        None => return None,
    };
    Some(if neg { -magnitude } else { magnitude })
}

/// Parse an integer written in decimal, `0x` hex or a leading-zero octal (as EDS files do,
/// CiA 306 §4.6).
pub fn parse_integer(text: &str) -> Option<i128> {
    let t = text.trim();
    let (neg, digits) = match t.strip_prefix('-') {
        Some(rest) => (true, rest),
        None => (false, t.strip_prefix('+').unwrap_or(t)),
    };
    // Digits only: `from_str_radix` would take a second sign ("-0-7", "0x+1").
    let (digits, radix) = if let Some(hex) = digits
        .strip_prefix("0x")
        .or_else(|| digits.strip_prefix("0X"))
    {
        (hex, 16)
    } else if digits.len() > 1 && digits.starts_with('0') {
        (&digits[1..], 8)
    } else {
        (digits, 10)
    };
    if digits.is_empty() || !digits.chars().all(|c| c.is_digit(radix)) {
        return None;
    }
    let magnitude = i128::from_str_radix(digits, radix).ok()?;
    if neg {
        magnitude.checked_neg()
    } else {
        Some(magnitude)
    }
}

/// Parse the text form of a `ty` value: integers in decimal or with a `0x` prefix in hex (a
/// number outside the type's range is [`TypeError::TooHigh`] or [`TypeError::TooLow`]).
pub fn from_text(ty: DataType, text: &str) -> Result<Value, TypeError> {
    use DataType::*;
    let bad = || invalid(ty, text);
    match ty {
        Boolean => match text.trim() {
            "0" | "false" | "FALSE" => Ok(Value::Bool(false)),
            "1" | "true" | "TRUE" => Ok(Value::Bool(true)),
            _ => Err(bad()),
        },
        _ if ty.is_signed() || ty.is_unsigned() => {
            let v = parse_text_integer(text).ok_or_else(bad)?;
            let (lo, hi) = ty.integer_range().ok_or_else(bad)?;
            let value = text.to_owned();
            if v > hi {
                return Err(TypeError::TooHigh { ty, value });
            }
            if v < lo {
                return Err(TypeError::TooLow { ty, value });
            }
            Ok(if ty.is_signed() {
                Value::Int(v as i64)
            } else {
                Value::Uint(v as u64)
            })
        }
        Real32 => text
            .trim()
            .parse::<f32>()
            .map(Value::Real32)
            .map_err(|_| bad()),
        Real64 => text
            .trim()
            .parse::<f64>()
            .map(Value::Real64)
            .map_err(|_| bad()),
        VisibleString | UnicodeString => {
            let v = Value::Text(text.to_owned());
            encode(ty, &v)?;
            Ok(v)
        }
        OctetString | Domain => parse_hex_bytes(ty, text).map(Value::Bytes),
        TimeDifference => {
            let total = text.trim().parse::<u64>().map_err(|_| bad())?;
            let days = u16::try_from(total / 86_400_000).map_err(|_| bad())?;
            Ok(Value::Time {
                ms: (total % 86_400_000) as u32,
                days,
            })
        }
        TimeOfDay => parse_time_of_day(text).ok_or_else(bad),
        _ => Err(bad()),
    }
}

fn parse_time_of_day(text: &str) -> Option<Value> {
    let (date, time) = text.trim().split_once('T')?;
    let mut d = date.split('-');
    let (y, m, day) = (
        d.next()?.parse().ok()?,
        d.next()?.parse().ok()?,
        d.next()?.parse().ok()?,
    );
    // Years outside what 16 bits of days since 1984 can hold are refused before the arithmetic,
    // which would overflow for years near the ends of i64.
    if d.next().is_some()
        || !(1..=12).contains(&m)
        || !(1..=31).contains(&day)
        || !(1984..=2164).contains(&y)
    {
        return None;
    }
    let (hms, fraction) = time.split_once('.').unwrap_or((time, "0"));
    if fraction.is_empty() || !fraction.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let mut t = hms.split(':');
    let (h, min, s): (u32, u32, u32) = (
        t.next()?.parse().ok()?,
        t.next()?.parse().ok()?,
        t.next()?.parse().ok()?,
    );
    let milli: u32 = format!("{fraction:0<3}")[..3].parse().ok()?;
    if t.next().is_some() || h > 23 || min > 59 || s > 59 {
        return None;
    }
    let days = days_from_civil(y, m, day) - CANOPEN_EPOCH_DAYS;
    Some(Value::Time {
        ms: ((h * 60 + min) * 60 + s) * 1000 + milli,
        days: u16::try_from(days).ok()?,
    })
}

/// Rust types that map to one CANopen type, for typed SDO reads and writes.
pub trait CanopenValue: Sized {
    /// The CANopen type this Rust type travels as.
    const TYPE: DataType;
    /// Encode for the wire.
    fn to_bytes(&self) -> Vec<u8>;
    /// Decode from the wire.
    fn from_bytes(bytes: &[u8]) -> Result<Self, TypeError>;
}

macro_rules! int_value {
    ($($t:ty => $dt:ident),*) => {$(
        impl CanopenValue for $t {
            const TYPE: DataType = DataType::$dt;
            fn to_bytes(&self) -> Vec<u8> {
                self.to_le_bytes().to_vec()
            }
            fn from_bytes(bytes: &[u8]) -> Result<Self, TypeError> {
                let arr = bytes.try_into().map_err(|_| TypeError::Length {
                    ty: Self::TYPE,
                    expected: std::mem::size_of::<$t>(),
                    got: bytes.len(),
                })?;
                Ok(<$t>::from_le_bytes(arr))
            }
        }
    )*};
}

int_value!(u8 => Unsigned8, u16 => Unsigned16, u32 => Unsigned32, u64 => Unsigned64,
    i8 => Integer8, i16 => Integer16, i32 => Integer32, i64 => Integer64,
    f32 => Real32, f64 => Real64);

impl CanopenValue for bool {
    const TYPE: DataType = DataType::Boolean;
    fn to_bytes(&self) -> Vec<u8> {
        vec![u8::from(*self)]
    }
    fn from_bytes(bytes: &[u8]) -> Result<Self, TypeError> {
        match decode(DataType::Boolean, bytes)? {
            Value::Bool(b) => Ok(b),
            _ => Err(invalid(DataType::Boolean, "?")),
        }
    }
}

impl CanopenValue for String {
    const TYPE: DataType = DataType::VisibleString;
    fn to_bytes(&self) -> Vec<u8> {
        self.chars()
            .map(|c| if (c as u32) < 0x100 { c as u8 } else { b'?' })
            .collect()
    }
    fn from_bytes(bytes: &[u8]) -> Result<Self, TypeError> {
        match decode(DataType::VisibleString, bytes)? {
            Value::Text(s) => Ok(s),
            _ => Err(invalid(DataType::VisibleString, "?")),
        }
    }
}

impl CanopenValue for Vec<u8> {
    const TYPE: DataType = DataType::Domain;
    fn to_bytes(&self) -> Vec<u8> {
        self.clone()
    }
    fn from_bytes(bytes: &[u8]) -> Result<Self, TypeError> {
        Ok(bytes.to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn sizes_and_codes() {
        assert_eq!(ALL_TYPES.len(), 25);
        for t in ALL_TYPES {
            assert_eq!(DataType::from_code(t.code()), Some(t));
            assert_eq!(DataType::from_name(&t.name().to_lowercase()), Some(t));
        }
        assert_eq!(DataType::Unsigned24.size(), Some(3));
        assert_eq!(
            DataType::Integer56.integer_range(),
            Some((-(1 << 55), (1 << 55) - 1))
        );
        assert_eq!(DataType::from_code(0x0E), None);
    }

    #[test]
    fn wire_encoding_is_little_endian_and_sized() {
        assert_eq!(
            encode(DataType::Unsigned24, &Value::Uint(0x123456)).unwrap(),
            [0x56, 0x34, 0x12]
        );
        assert_eq!(
            encode(DataType::Integer24, &Value::Int(-2)).unwrap(),
            [0xFE, 0xFF, 0xFF]
        );
        assert_eq!(
            decode(DataType::Integer24, &[0xFE, 0xFF, 0xFF]).unwrap(),
            Value::Int(-2)
        );
        assert_eq!(
            decode(DataType::Integer40, &[0, 0, 0, 0, 0x80]).unwrap(),
            Value::Int(-(1 << 39))
        );
        assert!(encode(DataType::Unsigned8, &Value::Uint(256)).is_err());
        assert!(encode(DataType::Integer8, &Value::Int(-129)).is_err());
        let err = decode(DataType::Unsigned32, &[1, 2]).unwrap_err();
        assert_eq!(err.abort_code(), AbortCode::LENGTH_TOO_LOW);
        assert_eq!(
            decode(DataType::VisibleString, b"lift\0\0").unwrap(),
            Value::Text("lift".into())
        );
        assert!(decode(DataType::Boolean, &[2]).is_err());
    }

    #[test]
    fn text_forms() {
        let cases: &[(DataType, &str)] = &[
            (DataType::Boolean, "1"),
            (DataType::Integer8, "-128"),
            (DataType::Unsigned64, "18446744073709551615"),
            (DataType::Real32, "0.1"),
            (DataType::Real64, "-1.5e300"),
            (DataType::Real64, "2"),
            (DataType::VisibleString, "Trip counter"),
            (DataType::UnicodeString, "Fahrkorb Türe ✓"),
            (DataType::OctetString, "00FF10"),
            (DataType::Domain, ""),
            (DataType::TimeOfDay, "2024-02-29T23:59:59.999"),
            (DataType::TimeDifference, "90061001"),
        ];
        for (ty, text) in cases {
            let v = from_text(*ty, text).unwrap();
            assert_eq!(to_text(*ty, &v), *text, "{ty}");
            let back = decode(*ty, &encode(*ty, &v).unwrap()).unwrap();
            assert_eq!(back, v, "{ty}");
        }
        assert_eq!(
            from_text(DataType::Unsigned16, "0x1017").unwrap(),
            Value::Uint(0x1017)
        );
        assert!(matches!(
            from_text(DataType::Unsigned8, "256"),
            Err(TypeError::TooHigh { .. })
        ));
        assert!(matches!(
            from_text(DataType::Unsigned8, "-1"),
            Err(TypeError::TooLow { .. })
        ));
        assert_eq!(
            from_text(DataType::Unsigned8, "010").unwrap(),
            Value::Uint(10),
            "decimal, not octal"
        );
        assert_eq!(
            from_text(DataType::Unsigned8, "08").unwrap(),
            Value::Uint(8)
        );
        assert_eq!(
            from_text(DataType::Integer8, "-0x10").unwrap(),
            Value::Int(-16)
        );
        assert!(from_text(DataType::Unsigned8, "0x").is_err());
        assert!(from_text(DataType::Integer16, "12a").is_err());
        assert!(from_text(DataType::OctetString, "ABC").is_err());
        assert!(
            from_text(DataType::VisibleString, "✓").is_err(),
            "not ISO 8859-1"
        );
        // Found by the `values` fuzz target: a NUL in a UNICODE_STRING did not survive the bus.
        assert!(
            from_text(DataType::UnicodeString, "\0\u{3}").is_err(),
            "a NUL ends the string on the bus"
        );
        assert!(
            from_text(DataType::TimeOfDay, "1983-12-31T00:00:00").is_err(),
            "before the epoch"
        );
        // Found by the `values` fuzz target: years near the ends of i64 overflowed the day count,
        // and a fraction of multi-byte characters was cut inside a character.
        for text in [
            "9223372036854775807-01-01T00:00:00",
            "-9223372036854775808-01-01T00:00:00",
            "2024-01-01T00:00:00.é日",
            "2024-01-01T00:00:00.",
            "2024-01-01T00:00:00.+5",
        ] {
            assert!(from_text(DataType::TimeOfDay, text).is_err(), "{text}");
        }
        assert!(from_text(DataType::TimeOfDay, "2163-06-06T00:00:00").is_ok());
        assert!(from_text(DataType::TimeOfDay, "2164-01-01T00:00:00").is_err());
    }

    #[test]
    fn eds_number_formats() {
        assert_eq!(parse_integer("0x1A"), Some(26));
        assert_eq!(parse_integer("017"), Some(15));
        assert_eq!(parse_integer("-5"), Some(-5));
        assert_eq!(parse_integer("0"), Some(0));
        assert_eq!(parse_integer("08"), None, "8 is not an octal digit");
        assert_eq!(parse_integer(""), None);
        // A second sign inside hex or octal digits (found by fuzzing: "-0-2000…" overflowed
        // when negated).
        assert_eq!(
            parse_integer("-0-200000000000000000000000000000000000000000000000"),
            None
        );
        assert_eq!(parse_integer("0x-1"), None);
        assert_eq!(parse_integer("0+7"), None);
        assert_eq!(
            parse_integer("-0x80000000000000000000000000000000"),
            None,
            "beyond i128"
        );
    }

    fn arb_value() -> impl Strategy<Value = (DataType, Value)> {
        proptest::sample::select(ALL_TYPES.to_vec()).prop_flat_map(|ty| {
            let v: BoxedStrategy<Value> = match ty {
                DataType::Boolean => any::<bool>().prop_map(Value::Bool).boxed(),
                DataType::Real32 => any::<f32>()
                    .prop_filter("nan", |f| !f.is_nan())
                    .prop_map(Value::Real32)
                    .boxed(),
                DataType::Real64 => any::<f64>()
                    .prop_filter("nan", |f| !f.is_nan())
                    .prop_map(Value::Real64)
                    .boxed(),
                DataType::VisibleString => "[ -~]{0,40}".prop_map(Value::Text).boxed(),
                DataType::UnicodeString => "[^\u{0}]{0,20}".prop_map(Value::Text).boxed(),
                DataType::OctetString | DataType::Domain => {
                    proptest::collection::vec(any::<u8>(), 0..64)
                        .prop_map(Value::Bytes)
                        .boxed()
                }
                DataType::TimeOfDay | DataType::TimeDifference => (0u32..86_400_000, any::<u16>())
                    .prop_map(|(ms, days)| Value::Time { ms, days })
                    .boxed(),
                _ => {
                    let (lo, hi) = ty.integer_range().unwrap();
                    if ty.is_signed() {
                        ((lo as i64)..=(hi as i64)).prop_map(Value::Int).boxed()
                    } else {
                        (0..=(hi as u64)).prop_map(Value::Uint).boxed()
                    }
                }
            };
            v.prop_map(move |v| (ty, v))
        })
    }

    proptest! {
        #[test]
        fn every_codec_round_trips((ty, value) in arb_value()) {
            let bytes = encode(ty, &value).unwrap();
            if let Some(size) = ty.size() {
                prop_assert_eq!(bytes.len(), size);
            }
            prop_assert_eq!(&decode(ty, &bytes).unwrap(), &value);
            let text = to_text(ty, &value);
            prop_assert_eq!(&from_text(ty, &text).unwrap(), &value, "text {}", text);
        }

        #[test]
        fn decoding_arbitrary_bytes_never_panics(code in 0u16..0x20, bytes in proptest::collection::vec(any::<u8>(), 0..16)) {
            if let Some(ty) = DataType::from_code(code) {
                if let Ok(v) = decode(ty, &bytes) {
                    let _ = to_text(ty, &v);
                }
            }
        }
    }
}
