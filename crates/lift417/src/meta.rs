//! The metadata vocabulary of the NXg connector (SW003 §8): object codes (§8.1, CiA 301 —
//! [`canopen::od::ObjectCode`]), physical units (§8.2), data types (§8.3), privileges (§8.4),
//! access (§8.5), and the presentation form ("formtype"), which the specification uses in its
//! samples (10, 15, 26) without listing; [`FormType`] documents our enumeration.

use std::fmt;

use canopen::types::DataType;

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
    /// Who may write an object (NXg SW003 §8.4), plus "engineer on site" (DESIGN.md §4), which
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
    /// The access of a CANopen sub-object.
    pub fn of(access: canopen::od::Access) -> Self {
        use canopen::od::Access as A;
        match access {
            A::Ro => Access::Ro,
            A::Wo => Access::Wo,
            A::Rw | A::Rwr | A::Rww => Access::Rw,
            A::Const => Access::Const,
        }
    }

    /// Whether the network may write it.
    pub fn writable(self) -> bool {
        matches!(self, Access::Rw | Access::Wo)
    }

    /// Parse "rw", "wo", "ro" or "const" (case-insensitive).
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

/// A data type code of the connector (NXg SW003 §8.3): the CiA 301 types, and four codes for
/// the communication records whose entries are UNSIGNED32.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum NxgDataType {
    /// A CiA 301 static data type.
    Cia(DataType),
    /// 0x20: PDO communication parameter.
    PdoCommunication,
    /// 0x21: PDO mapping.
    PdoMapping,
    /// 0x22: SDO parameter.
    SdoParameter,
    /// 0x23: identity.
    Identity,
}

impl NxgDataType {
    /// The number on the wire.
    pub fn code(self) -> u16 {
        match self {
            NxgDataType::Cia(t) => t.code(),
            NxgDataType::PdoCommunication => 0x20,
            NxgDataType::PdoMapping => 0x21,
            NxgDataType::SdoParameter => 0x22,
            NxgDataType::Identity => 0x23,
        }
    }

    /// The type with number `code`.
    pub fn from_code(code: u32) -> Result<Self, UnknownCode> {
        let unknown = UnknownCode {
            what: "data type",
            code,
        };
        match code {
            0x20 => Ok(NxgDataType::PdoCommunication),
            0x21 => Ok(NxgDataType::PdoMapping),
            0x22 => Ok(NxgDataType::SdoParameter),
            0x23 => Ok(NxgDataType::Identity),
            _ => u16::try_from(code)
                .ok()
                .and_then(DataType::from_code)
                .map(NxgDataType::Cia)
                .ok_or(unknown),
        }
    }

    /// The CiA 301 type the values have (UNSIGNED32 for the record codes).
    pub fn value_type(self) -> DataType {
        match self {
            NxgDataType::Cia(t) => t,
            _ => DataType::Unsigned32,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
    }

    #[test]
    fn access_and_data_types() {
        assert_eq!(Access::of(canopen::od::Access::Rww), Access::Rw);
        assert_eq!(Access::parse("CONST"), Ok(Access::Const));
        assert!(Access::parse("rwr").is_err());
        assert_eq!(
            NxgDataType::from_code(7),
            Ok(NxgDataType::Cia(DataType::Unsigned32))
        );
        assert_eq!(NxgDataType::from_code(0x21), Ok(NxgDataType::PdoMapping));
        assert_eq!(NxgDataType::PdoMapping.value_type(), DataType::Unsigned32);
        assert_eq!(NxgDataType::from_code(0x0E).map_err(|e| e.code), Err(0x0E));
        for code in [1u32, 0x0F, 0x1B, 0x20, 0x23] {
            assert_eq!(
                u32::from(NxgDataType::from_code(code).unwrap().code()),
                code
            );
        }
    }
}
