//! The metadata vocabulary of the NXg connector (SW003 §8): object codes (§8.1), physical units
//! (§8.2), data types (§8.3), privileges (§8.4), access (§8.5), and the presentation form
//! ("formtype"), which the specification uses in its samples (10, 15, 26) without listing;
//! [`FormType`] documents our enumeration. [`Description`] puts them together: everything a
//! gateway reports about a sub-object besides its value (NXg §6.1.1), with names and hints per
//! language ([`Texts`]) and limits ([`Bound`]).
//!
//! This module needs no CANopen stack (the portal uses it); with the `gateway` feature it also
//! converts from and to the CiA 301 types of the `canopen` crate.

use std::collections::BTreeMap;
use std::fmt;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

/// An unknown code in one of the enumerations.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("{what} {code} is not defined by NXg SW003 §8")]
pub struct UnknownCode {
    /// Which enumeration.
    pub what: &'static str,
    /// The code.
    pub code: u32,
}

macro_rules! code_enum {
    ($(#[$doc:meta])* $name:ident : $what:literal { $($(#[$vdoc:meta])* $variant:ident = $code:literal => $text:literal,)* }) => {
        $(#[$doc])*
        #[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
        #[repr(u8)]
        pub enum $name {
            $($(#[$vdoc])* $variant = $code,)*
        }

        impl $name {
            /// Every value, in code order.
            pub const ALL: &'static [$name] = &[$($name::$variant,)*];

            /// The number on the wire.
            pub fn code(self) -> u8 {
                self as u8
            }

            /// The value with number `code`.
            pub fn from_code(code: u32) -> Result<Self, UnknownCode> {
                Self::ALL
                    .iter()
                    .copied()
                    .find(|v| u32::from(v.code()) == code)
                    .ok_or(UnknownCode { what: $what, code })
            }

            /// The specification's text for the value.
            pub fn text(self) -> &'static str {
                match self {
                    $($name::$variant => $text,)*
                }
            }
        }

        impl fmt::Display for $name {
            fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
                f.write_str(self.text())
            }
        }
    };
}

code_enum! {
    /// Physical units (NXg SW003 §8.2): CiA 303 base and supplementary SI units plus the
    /// connector's own. [`PhysUnit::text`] is the symbol shown next to a value.
    PhysUnit: "physical unit" {
        /// No unit.
        None = 0 => "",
        /// Metre.
        Metre = 1 => "m",
        /// Kilogram.
        Kilogram = 2 => "kg",
        /// Second.
        Second = 3 => "s",
        /// Ampere.
        Ampere = 4 => "A",
        /// Kelvin.
        Kelvin = 5 => "K",
        /// Mole.
        Mole = 6 => "mol",
        /// Candela.
        Candela = 7 => "cd",
        /// Percent.
        Percent = 8 => "%",
        /// Per mille.
        PerMille = 9 => "‰",
        /// Volt.
        Volt = 10 => "V",
        /// Millisecond.
        Millisecond = 11 => "ms",
        /// Minute.
        Minute = 12 => "min",
        /// Hour.
        Hour = 13 => "h",
        /// Day.
        Day = 14 => "d",
        /// Millimetre.
        Millimetre = 15 => "mm",
        /// Radian.
        Radian = 16 => "rad",
        /// Steradian.
        Steradian = 17 => "sr",
        /// Millimetre per second.
        MillimetrePerSecond = 18 => "mm/s",
        /// Millimetre per second squared.
        MillimetrePerSecond2 = 19 => "mm/s²",
        /// Millimetre per second cubed (jerk).
        MillimetrePerSecond3 = 20 => "mm/s³",
        /// Bit per second.
        BitPerSecond = 21 => "Bit/s",
        /// Kilobit per second.
        KilobitPerSecond = 22 => "kBit/s",
        /// Degree Celsius.
        Celsius = 23 => "°C",
        /// Encoder increments.
        Increments = 24 => "increments",
        /// kg or %, as 0x6480 sub 2 "Load value – SI unit" says (CiA 417).
        LoadUnit = 25 => "kg|%",
        /// Trips (travels).
        Trips = 26 => "trips",
        /// Gravity (g).
        Gravity = 27 => "g",
        /// Millimetre per increment.
        MillimetrePerIncrement = 28 => "mm/inc",
        /// Watt.
        Watt = 29 => "W",
        /// Watt hour.
        WattHour = 30 => "Wh",
        /// A node-ID.
        NodeId = 31 => "node-ID",
        /// Revolutions per minute.
        Rpm = 32 => "rpm",
        /// Hertz.
        Hertz = 33 => "Hz",
        /// Inch.
        Inch = 34 => "in",
        /// Feet per minute.
        FeetPerMinute = 35 => "fpm",
        /// Pound.
        Pound = 36 => "lb",
        /// Degree Fahrenheit.
        Fahrenheit = 37 => "°F",
        /// Feet per second squared.
        FeetPerSecond2 = 38 => "ft/s²",
        /// Feet per second cubed.
        FeetPerSecond3 = 39 => "ft/s³",
        /// Foot.
        Foot = 40 => "ft",
        /// Temperature difference in °C.
        DeltaCelsius = 41 => "Δ°C",
        /// Temperature difference in °F.
        DeltaFahrenheit = 42 => "Δ°F",
        /// Switching cycles.
        SwitchingCycles = 43 => "switching cycles",
    }
}

code_enum! {
    /// Who may write an object (NXg SW003 §8.4), plus "engineer on site" (docs/PROTOCOL.md §Privileges), which
    /// only a person at the lift can have: it is never granted remotely.
    Privilege: "privilege" {
        /// Any portal user.
        User = 0 => "user",
        /// Service technicians.
        Service = 1 => "service",
        /// Set-up (commissioning) rights.
        Setup = 2 => "setup",
        /// Only locally, never through the connector.
        EngineerOnSite = 3 => "engineer on site",
    }
}

impl Privilege {
    /// Whether `elevate_privilege` may grant this level.
    pub fn grantable_remotely(self) -> bool {
        self != Privilege::EngineerOnSite
    }
}

code_enum! {
    /// How a portal presents a value (the "formtype" of `get_canopen_object`).
    ///
    /// NXg SW003 uses 10 (the trip counter), 15 (hall lantern options, with a `list`) and 26 (the
    /// floor level positions, read `compact`) without defining the enumeration. Ours keeps those
    /// three meanings and adds the forms a lift portal needs; the gaps leave room to extend.
    FormType: "formtype" {
        /// Shown as it comes, no interpretation.
        Raw = 0 => "raw",
        /// Free text (VISIBLE_STRING, UNICODE_STRING).
        Text = 1 => "text",
        /// Hexadecimal (codes, identifiers, octet strings).
        Hex = 2 => "hex",
        /// On/off switch (0 = off, 1 = on).
        Switch = 3 => "switch",
        /// One flag per bit; `list` names the bits from bit 0.
        Bits = 4 => "bits",
        /// A number with its unit (counters, measurements, parameters) — the trip counter.
        Number = 10 => "number",
        /// A real number with its unit.
        Real = 11 => "real",
        /// A duration in its unit; with `show_off_at_zero` / `show_unlimited_at_max`.
        Duration = 12 => "duration",
        /// A date and time (TIME_OF_DAY).
        DateTime = 13 => "date and time",
        /// One entry of `list`, chosen by its position (min..=max) — hall lantern options.
        Choice = 15 => "choice",
        /// Writing performs an action (a call, a reset); the value read carries no meaning.
        Command = 20 => "command",
        /// An array of numbers shown as a table, one row per sub-index — floor level positions.
        Table = 26 => "table",
    }
}

code_enum! {
    /// Access as the connector reports it (NXg SW003 §8.5). CANopen's rwr/rww (PDO direction
    /// hints) are "rw" here.
    Access: "access" {
        /// Read and write.
        Rw = 0 => "rw",
        /// Write only.
        Wo = 1 => "wo",
        /// Read only.
        Ro = 2 => "ro",
        /// Read only, never changes.
        Const = 3 => "const",
    }
}

impl Access {
    /// Whether the connector may write it.
    pub fn writable(self) -> bool {
        matches!(self, Access::Rw | Access::Wo)
    }

    /// Parse `rw`, `wo`, `ro` or `const` (any case).
    pub fn parse(text: &str) -> Result<Self, UnknownCode> {
        Self::ALL
            .iter()
            .copied()
            .find(|a| a.text().eq_ignore_ascii_case(text.trim()))
            .ok_or(UnknownCode {
                what: "access",
                code: u32::MAX,
            })
    }
}

code_enum! {
    /// Object codes (NXg SW003 §8.1, from CiA 301 §7.4.3).
    ObjCode: "object code" {
        /// An entry without data.
        Null = 0 => "NULL",
        /// A large amount of data.
        Domain = 2 => "DOMAIN",
        /// A type definition.
        DefType = 5 => "DEFTYPE",
        /// A structure definition.
        DefStruct = 6 => "DEFSTRUCT",
        /// A single value.
        Var = 7 => "VAR",
        /// Several values of one type.
        Array = 8 => "ARRAY",
        /// Several values of different types.
        Record = 9 => "RECORD",
    }
}

/// A data type as the connector reports it (NXg SW003 §8.3): a CiA 301 basic data type code
/// (01h–1Bh, as CiA 301 §7.4.7 numbers them) or one of the four structure codes 20h–23h, whose
/// entries carry UNSIGNED32 values.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(try_from = "u32", into = "u16")]
pub struct DataType(u16);

impl DataType {
    /// BOOLEAN.
    pub const BOOLEAN: DataType = DataType(0x01);
    /// UNSIGNED8.
    pub const UNSIGNED8: DataType = DataType(0x05);
    /// UNSIGNED16.
    pub const UNSIGNED16: DataType = DataType(0x06);
    /// UNSIGNED32.
    pub const UNSIGNED32: DataType = DataType(0x07);
    /// VISIBLE_STRING.
    pub const VISIBLE_STRING: DataType = DataType(0x09);
    /// PDO communication parameter record (UNSIGNED32 entries).
    pub const PDO_COMMUNICATION: DataType = DataType(0x20);
    /// PDO mapping record.
    pub const PDO_MAPPING: DataType = DataType(0x21);
    /// SDO parameter record.
    pub const SDO_PARAMETER: DataType = DataType(0x22);
    /// Identity record.
    pub const IDENTITY: DataType = DataType(0x23);

    /// The number on the wire.
    pub fn code(self) -> u16 {
        self.0
    }

    /// The data type with number `code`, if §8.3 lists it (`const`: the catalog's static
    /// tables are checked by the compiler).
    pub const fn from_code(code: u32) -> Result<Self, UnknownCode> {
        match code {
            0x01..=0x0D | 0x0F..=0x16 | 0x18..=0x1B | 0x20..=0x23 => Ok(DataType(code as u16)),
            _ => Err(UnknownCode {
                what: "data type",
                code,
            }),
        }
    }

    /// One of the structure codes 20h–23h (values are UNSIGNED32).
    pub fn is_structure(self) -> bool {
        self.0 >= 0x20
    }
}

impl TryFrom<u32> for DataType {
    type Error = UnknownCode;

    fn try_from(code: u32) -> Result<Self, UnknownCode> {
        DataType::from_code(code)
    }
}

impl From<DataType> for u16 {
    fn from(t: DataType) -> u16 {
        t.0
    }
}

/// Texts by language tag (`en`, `de`, …): the names, hints and list entries of NXg §6.1.1.
/// Shared, not copied, between the entries that use the same texts (an object's hint serves all
/// its sub-indices), which keeps a catalog small; texts of static tables (the built-in CiA 417
/// catalog) are borrowed from them, so describing an object allocates nothing for its texts.
#[derive(Clone, Deserialize)]
#[serde(from = "BTreeMap<String, String>")]
pub struct Texts(Repr);

#[derive(Clone)]
enum Repr {
    /// Texts read at run time (a vendor file, an EDS), by language.
    Shared(Arc<BTreeMap<String, String>>),
    /// Texts of static tables: (language, text) pairs of `pool`, in language order.
    Pooled {
        pool: &'static str,
        pairs: &'static [PooledText],
    },
    /// Texts of tables read at run time (a vendor's metadata file): the pairs `start..start +
    /// len` of the pool's, shared, not copied.
    SharedPool {
        pool: Arc<TextPool>,
        start: u32,
        len: u32,
    },
}

/// Texts read at run time, each string once, and the (language, text) pairs that locate the
/// texts of each [`Texts`] in them: what [`Texts::shared_pool`] points into.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TextPool {
    /// Every string.
    pub strings: Box<str>,
    /// Pairs of `strings`, a run of them per [`Texts`].
    pub pairs: Box<[PooledText]>,
}

/// Where one (language, text) pair of [`Texts::pooled`] lies in its pool: byte offsets and
/// lengths. Plain numbers, so that tables of them need no relocation when a program starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PooledText {
    /// Start of the language tag.
    pub lang_start: u32,
    /// Length of the language tag.
    pub lang_len: u32,
    /// Start of the text.
    pub text_start: u32,
    /// Length of the text.
    pub text_len: u32,
}

impl Default for Texts {
    fn default() -> Texts {
        Texts(Repr::Pooled {
            pool: "",
            pairs: &[],
        })
    }
}

impl PartialEq for Texts {
    fn eq(&self, other: &Texts) -> bool {
        self.pairs().eq(other.pairs())
    }
}

impl Eq for Texts {}

impl fmt::Debug for Texts {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_map().entries(self.pairs()).finish()
    }
}

impl From<BTreeMap<String, String>> for Texts {
    fn from(map: BTreeMap<String, String>) -> Texts {
        Texts(Repr::Shared(Arc::new(map)))
    }
}

impl Texts {
    /// The texts `pairs` of `pool` locate (in language order, as a `BTreeMap` keeps them): a
    /// view of static tables, nothing copied. A pair outside the pool is left out.
    pub fn pooled(pool: &'static str, pairs: &'static [PooledText]) -> Texts {
        Texts(Repr::Pooled { pool, pairs })
    }

    /// The texts the pool's pairs `start..start + len` locate (in language order): a view of
    /// tables read at run time, shared by every description that uses them. A pair outside the
    /// strings, or a range outside the pairs, is left out.
    pub fn shared_pool(pool: &Arc<TextPool>, start: u32, len: u32) -> Texts {
        Texts(Repr::SharedPool {
            pool: pool.clone(),
            start,
            len,
        })
    }

    /// Every (language, text), in language order.
    pub fn pairs(&self) -> impl Iterator<Item = (&str, &str)> {
        let (shared, pooled) = match &self.0 {
            Repr::Shared(map) => (Some(map.iter()), None),
            Repr::Pooled { pool, pairs } => (None, Some((*pool, pairs.iter()))),
            Repr::SharedPool { pool, start, len } => {
                let start = *start as usize;
                let range = start..start.saturating_add(*len as usize);
                let pairs = pool.pairs.get(range).unwrap_or_default();
                (None, Some((&*pool.strings, pairs.iter())))
            }
        };
        let shared = shared
            .into_iter()
            .flatten()
            .map(|(l, t)| (l.as_str(), t.as_str()));
        let pooled = pooled.into_iter().flat_map(|(pool, pairs)| {
            pairs.filter_map(move |p| {
                let at = |start: u32, len: u32| {
                    let start = start as usize;
                    pool.get(start..start.checked_add(len as usize)?)
                };
                Some((at(p.lang_start, p.lang_len)?, at(p.text_start, p.text_len)?))
            })
        });
        shared.chain(pooled)
    }

    /// The text in `lang` (case-insensitive), if there is one.
    pub fn get(&self, lang: &str) -> Option<&str> {
        self.entry(lang).map(|(_, t)| t)
    }

    /// The same text in every language (names taken from an EDS).
    pub fn english(text: &str) -> Texts {
        BTreeMap::from([("en".to_owned(), text.to_owned())]).into()
    }

    /// A text in English and German (canlift's own vocabulary: profile tables, EMCY texts).
    pub fn en_de(en: &str, de: &str) -> Texts {
        BTreeMap::from([
            ("en".to_owned(), en.to_owned()),
            ("de".to_owned(), de.to_owned()),
        ])
        .into()
    }

    /// The languages present.
    pub fn languages(&self) -> impl Iterator<Item = &str> {
        self.pairs().map(|(l, _)| l)
    }

    /// Whether no language has a text.
    pub fn is_empty(&self) -> bool {
        self.pairs().next().is_none()
    }

    /// (language, text) of the first of `langs` present (case-insensitive).
    pub fn first_of<'a, 'b>(
        &'a self,
        langs: impl IntoIterator<Item = &'b str>,
    ) -> Option<(&'a str, &'a str)> {
        langs.into_iter().find_map(|l| self.entry(l))
    }

    fn entry(&self, lang: &str) -> Option<(&str, &str)> {
        self.pairs().find(|(l, _)| l.eq_ignore_ascii_case(lang))
    }

    /// These texts with `other`'s on top: a language both have takes `other`'s text.
    pub fn overlay(&self, other: &Texts) -> Texts {
        if other.is_empty() {
            return self.clone();
        }
        // The usual case (an EDS's English name under the catalog's or a vendor's texts):
        // `other` has every language, so it is the answer, shared rather than copied.
        if self.languages().all(|l| other.languages().any(|o| o == l)) {
            return other.clone();
        }
        self.pairs()
            .chain(other.pairs())
            .map(|(l, t)| (l.to_owned(), t.to_owned()))
            .collect::<BTreeMap<_, _>>()
            .into()
    }

    /// These texts with `name` as the English one where they have none: an EDS's name under
    /// the NXg texts of the same object ([`Self::overlay`] without making the English text
    /// when it would be covered).
    pub fn or_english(self, name: &str) -> Texts {
        if self.languages().any(|l| l == "en") {
            self
        } else {
            Texts::english(name).overlay(&self)
        }
    }

    /// The texts with every `key` replaced by `value`; shared when none contains it.
    pub fn fill(&self, key: &str, value: u16) -> Texts {
        if !self.pairs().any(|(_, t)| t.contains(key)) {
            return self.clone();
        }
        self.pairs()
            .map(|(l, t)| (l.to_owned(), t.replace(key, &value.to_string())))
            .collect::<BTreeMap<_, _>>()
            .into()
    }
}

/// A limit: an integer (any CiA integer type fits an `i128`) or a real.
#[derive(Debug, Clone, Copy, PartialEq, Deserialize)]
#[serde(from = "RawBound")]
pub enum Bound {
    /// Integer types and string lengths.
    Int(i128),
    /// REAL32 / REAL64.
    Real(f64),
}

/// TOML integers are 64-bit; every limit a file gives fits.
#[derive(Deserialize)]
#[serde(untagged)]
enum RawBound {
    Int(i64),
    Real(f64),
}

impl From<RawBound> for Bound {
    fn from(raw: RawBound) -> Bound {
        match raw {
            RawBound::Int(v) => Bound::Int(v.into()),
            RawBound::Real(v) => Bound::Real(v),
        }
    }
}

impl Bound {
    /// As a real number, for comparisons across kinds.
    pub fn as_f64(self) -> f64 {
        match self {
            Bound::Int(v) => v as f64,
            Bound::Real(v) => v,
        }
    }

    /// As a JSON number (`min`/`max` of NXg §6.1.1); `None` for an integer beyond 64 bits.
    pub fn to_json(self) -> Option<serde_json::Number> {
        match self {
            Bound::Int(v) => i64::try_from(v)
                .map(serde_json::Number::from)
                .or_else(|_| u64::try_from(v).map(serde_json::Number::from))
                .ok(),
            Bound::Real(v) => serde_json::Number::from_f64(v),
        }
    }
}

/// Presentation hints of `get_canopen_object` (NXg SW003 §6.1.1).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[serde(default)]
pub struct Hints {
    /// Show 0 as "off".
    pub show_off_at_zero: bool,
    /// Show `max` as "unlimited".
    pub show_unlimited_at_max: bool,
    /// Show `max` as "undefined".
    pub show_undefined_at_max: bool,
}

/// What a gateway says about a sub-object besides its value (NXg SW003 §6.1.1): how to read,
/// show and write it, its limits and its texts per language.
#[derive(Debug, Clone, PartialEq)]
pub struct Description {
    /// The object code of the object the sub-object belongs to (§8.1).
    pub objcode: ObjCode,
    /// Data type (§8.3).
    pub datatype: DataType,
    /// How a portal presents the value.
    pub formtype: FormType,
    /// Physical unit (§8.2).
    pub physunit: PhysUnit,
    /// Access (§8.5).
    pub access: Access,
    /// Privilege needed to write (§8.4).
    pub privilege: Privilege,
    /// Name per language.
    pub name: Texts,
    /// Help text per language.
    pub hint: Texts,
    /// Lowest value (strings: none).
    pub min: Option<Bound>,
    /// Highest value (strings: most characters).
    pub max: Option<Bound>,
    /// 0 is valid although outside `min..=max`.
    pub zero: bool,
    /// Texts for the values `min..=max` (choice) or for the bits from bit 0 (bits).
    pub list: Vec<Texts>,
    /// Presentation hints.
    pub hints: Hints,
}

/// The CiA 301 types of the `canopen` crate in the connector's vocabulary, and back.
#[cfg(feature = "gateway")]
mod cia301 {
    use super::{Access, DataType, ObjCode};
    use canopen::od;
    use canopen::types;

    impl DataType {
        /// The CiA 301 type of the values: UNSIGNED32 for the structure codes 20h–23h.
        pub fn value_type(self) -> types::DataType {
            types::DataType::from_code(self.0).unwrap_or(types::DataType::Unsigned32)
        }
    }

    impl From<types::DataType> for DataType {
        fn from(t: types::DataType) -> DataType {
            DataType(t.code())
        }
    }

    impl From<od::ObjectCode> for ObjCode {
        fn from(code: od::ObjectCode) -> ObjCode {
            match code {
                od::ObjectCode::Null => ObjCode::Null,
                od::ObjectCode::Domain => ObjCode::Domain,
                od::ObjectCode::DefType => ObjCode::DefType,
                od::ObjectCode::DefStruct => ObjCode::DefStruct,
                od::ObjectCode::Var => ObjCode::Var,
                od::ObjectCode::Array => ObjCode::Array,
                od::ObjectCode::Record => ObjCode::Record,
            }
        }
    }

    impl From<od::Access> for Access {
        /// CANopen's rwr/rww (PDO direction hints) are "rw" to the connector.
        fn from(access: od::Access) -> Access {
            match access {
                od::Access::Ro => Access::Ro,
                od::Access::Wo => Access::Wo,
                od::Access::Rw | od::Access::Rwr | od::Access::Rww => Access::Rw,
                od::Access::Const => Access::Const,
            }
        }
    }

    #[cfg(test)]
    mod tests {
        use super::*;

        #[test]
        fn conversions() {
            assert_eq!(Access::from(od::Access::Rww), Access::Rw);
            assert_eq!(
                DataType::from(types::DataType::Unsigned32),
                DataType::UNSIGNED32
            );
            assert_eq!(
                DataType::PDO_MAPPING.value_type(),
                types::DataType::Unsigned32
            );
            for t in types::ALL_TYPES {
                assert_eq!(DataType::from(t).value_type(), t);
                assert!(DataType::from_code(u32::from(t.code())).is_ok(), "{t:?}");
            }
            assert_eq!(ObjCode::from(od::ObjectCode::Record), ObjCode::Record);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pooled_texts_read_as_shared_ones() {
        static POOL: &str = "deFahrtenenTrips {i}";
        static PAIRS: [PooledText; 3] = [
            PooledText {
                lang_start: 0,
                lang_len: 2,
                text_start: 2,
                text_len: 7,
            },
            PooledText {
                lang_start: 9,
                lang_len: 2,
                text_start: 11,
                text_len: 9,
            },
            // Outside the pool: left out, not a panic.
            PooledText {
                lang_start: 40,
                lang_len: 2,
                text_start: 0,
                text_len: 2,
            },
        ];
        let pooled = Texts::pooled(POOL, &PAIRS);
        let shared = Texts::en_de("Trips {i}", "Fahrten");
        assert_eq!(pooled, shared);
        // The same over shared tables read at run time; a range beyond them reads as none.
        let pool = Arc::new(TextPool {
            strings: POOL.into(),
            pairs: PAIRS[..].into(),
        });
        assert_eq!(Texts::shared_pool(&pool, 0, 3), shared);
        assert_eq!(Texts::shared_pool(&pool, 1, 1), Texts::english("Trips {i}"));
        assert!(Texts::shared_pool(&pool, 2, 5).is_empty());
        assert_eq!(format!("{pooled:?}"), format!("{shared:?}"));
        assert_eq!(pooled.get("EN"), Some("Trips {i}"));
        assert_eq!(pooled.first_of(["fr", "de"]), Some(("de", "Fahrten")));
        assert_eq!(pooled.languages().collect::<Vec<_>>(), ["de", "en"]);
        assert_eq!(pooled.fill("{i}", 3).get("en"), Some("Trips 3"));
        let french = BTreeMap::from([("fr".to_owned(), "Courses".to_owned())]).into();
        let more = pooled.overlay(&french);
        assert_eq!(more.languages().collect::<Vec<_>>(), ["de", "en", "fr"]);
        assert!(Texts::default().is_empty() && !pooled.is_empty());
        assert_eq!(Texts::default(), BTreeMap::new().into());
    }

    #[test]
    fn codes_round_trip_and_match_the_specification() {
        assert_eq!(PhysUnit::ALL.len(), 44, "0..=43");
        for (i, u) in PhysUnit::ALL.iter().enumerate() {
            assert_eq!(usize::from(u.code()), i, "{u:?}");
            assert_eq!(PhysUnit::from_code(u.code().into()), Ok(*u));
        }
        assert_eq!(PhysUnit::from_code(26).unwrap().text(), "trips");
        assert_eq!(PhysUnit::from_code(15).unwrap(), PhysUnit::Millimetre);
        assert_eq!(
            PhysUnit::from_code(44),
            Err(UnknownCode {
                what: "physical unit",
                code: 44
            })
        );
        for p in Privilege::ALL {
            assert_eq!(Privilege::from_code(p.code().into()), Ok(*p));
        }
        assert!(!Privilege::EngineerOnSite.grantable_remotely());
        assert!(Privilege::Setup.grantable_remotely());
        // The formtypes of the specification's samples.
        assert_eq!(FormType::from_code(10), Ok(FormType::Number));
        assert_eq!(FormType::from_code(15), Ok(FormType::Choice));
        assert_eq!(FormType::from_code(26), Ok(FormType::Table));
        assert!(FormType::from_code(5).is_err());
        for f in FormType::ALL {
            assert_eq!(FormType::from_code(f.code().into()), Ok(*f));
        }
        assert_eq!(ObjCode::from_code(8), Ok(ObjCode::Array));
        assert!(ObjCode::from_code(3).is_err());
    }

    #[test]
    fn access_and_data_types() {
        assert_eq!(Access::parse("CONST"), Ok(Access::Const));
        assert!(Access::parse("rwr").is_err());
        assert_eq!(DataType::from_code(7), Ok(DataType::UNSIGNED32));
        assert_eq!(DataType::from_code(0x21), Ok(DataType::PDO_MAPPING));
        assert!(DataType::PDO_MAPPING.is_structure());
        assert_eq!(DataType::from_code(0x0E).map_err(|e| e.code), Err(0x0E));
        assert_eq!(DataType::from_code(0x17).map_err(|e| e.code), Err(0x17));
        for code in [1u32, 0x0F, 0x1B, 0x20, 0x23] {
            assert_eq!(u32::from(DataType::from_code(code).unwrap().code()), code);
        }
        let t: DataType = serde_json::from_str("9").unwrap();
        assert_eq!(t, DataType::VISIBLE_STRING);
        assert!(serde_json::from_str::<DataType>("14").is_err());
    }

    #[test]
    fn texts_by_language() {
        let t = Texts::from(BTreeMap::from([
            ("en".to_owned(), "Floor {n}".to_owned()),
            ("de".to_owned(), "Etage {n}".to_owned()),
        ]));
        assert_eq!(t.get("DE"), Some("Etage {n}"));
        assert_eq!(t.first_of(["fr", "de"]), Some(("de", "Etage {n}")));
        assert_eq!(t.fill("{n}", 3).get("en"), Some("Floor 3"));
        let eds = Texts::english("Door hold time");
        let vendor = Texts::from(BTreeMap::from([(
            "de".to_owned(),
            "Türoffenhaltezeit".to_owned(),
        )]));
        let both = eds.overlay(&vendor);
        assert_eq!(
            (both.get("en"), both.get("de")),
            (Some("Door hold time"), Some("Türoffenhaltezeit"))
        );
        // Texts with every language of the EDS's name replace it whole.
        assert_eq!(eds.overlay(&t), t);
        assert_eq!(t.clone().or_english("Door hold time"), t);
        assert_eq!(vendor.clone().or_english("Door hold time"), both);
        assert_eq!(
            t.overlay(&eds).languages().collect::<Vec<_>>(),
            ["de", "en"]
        );
        assert_eq!(t.overlay(&eds).get("en"), Some("Door hold time"));
        assert_eq!(
            Bound::Int(4_294_967_295).to_json(),
            Some(4_294_967_295u64.into())
        );
        assert_eq!(Bound::Int(-5).to_json(), Some((-5i64).into()));
        assert_eq!(Bound::Int(i128::MAX).to_json(), None);
    }
}
