//! SDO abort codes (CiA 301 §7.2.4.3.17, table 22).

/// A CiA 301 SDO abort code with its standard meaning.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct AbortCode(pub u32);

/// Every abort code CiA 301 defines, with the specification's wording.
const TABLE: &[(u32, &str)] = &[
    (0x0503_0000, "Toggle bit not alternated"),
    (0x0504_0000, "SDO protocol timed out"),
    (0x0504_0001, "Client/server command specifier not valid or unknown"),
    (0x0504_0002, "Invalid block size"),
    (0x0504_0003, "Invalid sequence number"),
    (0x0504_0004, "CRC error"),
    (0x0504_0005, "Out of memory"),
    (0x0601_0000, "Unsupported access to an object"),
    (0x0601_0001, "Attempt to read a write only object"),
    (0x0601_0002, "Attempt to write a read only object"),
    (0x0602_0000, "Object does not exist in the object dictionary"),
    (0x0604_0041, "Object cannot be mapped to the PDO"),
    (0x0604_0042, "The number and length of the objects to be mapped would exceed PDO length"),
    (0x0604_0043, "General parameter incompatibility reason"),
    (0x0604_0047, "General internal incompatibility in the device"),
    (0x0606_0000, "Access failed due to a hardware error"),
    (0x0607_0010, "Data type does not match, length of service parameter does not match"),
    (0x0607_0012, "Data type does not match, length of service parameter too high"),
    (0x0607_0013, "Data type does not match, length of service parameter too low"),
    (0x0609_0011, "Sub-index does not exist"),
    (0x0609_0030, "Invalid value for parameter (download only)"),
    (0x0609_0031, "Value of parameter written too high (download only)"),
    (0x0609_0032, "Value of parameter written too low (download only)"),
    (0x0609_0036, "Maximum value is less than minimum value"),
    (0x060A_0023, "Resource not available: SDO connection"),
    (0x0800_0000, "General error"),
    (0x0800_0020, "Data cannot be transferred or stored to the application"),
    (0x0800_0021, "Data cannot be transferred or stored to the application because of local control"),
    (0x0800_0022, "Data cannot be transferred or stored to the application because of the present device state"),
    (0x0800_0023, "Object dictionary dynamic generation fails or no object dictionary is present"),
    (0x0800_0024, "No data available"),
];

#[allow(missing_docs)]
impl AbortCode {
    pub const TOGGLE: Self = Self(0x0503_0000);
    pub const TIMEOUT: Self = Self(0x0504_0000);
    pub const COMMAND: Self = Self(0x0504_0001);
    pub const BLOCK_SIZE: Self = Self(0x0504_0002);
    pub const SEQUENCE: Self = Self(0x0504_0003);
    pub const CRC: Self = Self(0x0504_0004);
    pub const OUT_OF_MEMORY: Self = Self(0x0504_0005);
    pub const UNSUPPORTED_ACCESS: Self = Self(0x0601_0000);
    pub const WRITE_ONLY: Self = Self(0x0601_0001);
    pub const READ_ONLY: Self = Self(0x0601_0002);
    pub const NO_OBJECT: Self = Self(0x0602_0000);
    pub const NOT_MAPPABLE: Self = Self(0x0604_0041);
    pub const PDO_LENGTH: Self = Self(0x0604_0042);
    pub const PARAMETER_INCOMPATIBLE: Self = Self(0x0604_0043);
    pub const INTERNAL_INCOMPATIBLE: Self = Self(0x0604_0047);
    pub const HARDWARE: Self = Self(0x0606_0000);
    pub const LENGTH_MISMATCH: Self = Self(0x0607_0010);
    pub const LENGTH_TOO_HIGH: Self = Self(0x0607_0012);
    pub const LENGTH_TOO_LOW: Self = Self(0x0607_0013);
    pub const NO_SUB_INDEX: Self = Self(0x0609_0011);
    pub const INVALID_VALUE: Self = Self(0x0609_0030);
    pub const VALUE_TOO_HIGH: Self = Self(0x0609_0031);
    pub const VALUE_TOO_LOW: Self = Self(0x0609_0032);
    pub const MAX_LESS_THAN_MIN: Self = Self(0x0609_0036);
    pub const NO_RESOURCE: Self = Self(0x060A_0023);
    pub const GENERAL: Self = Self(0x0800_0000);
    pub const CANNOT_STORE: Self = Self(0x0800_0020);
    pub const LOCAL_CONTROL: Self = Self(0x0800_0021);
    pub const DEVICE_STATE: Self = Self(0x0800_0022);
    pub const NO_DICTIONARY: Self = Self(0x0800_0023);
    pub const NO_DATA: Self = Self(0x0800_0024);

    /// The specification's description, if the code is a standard one.
    pub fn description(self) -> Option<&'static str> {
        TABLE.iter().find(|(c, _)| *c == self.0).map(|(_, d)| *d)
    }
}

impl std::error::Error for AbortCode {}

impl std::fmt::Display for AbortCode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.description() {
            Some(d) => write!(f, "{:08X} ({d})", self.0),
            None => write!(f, "{:08X}", self.0),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_and_unknown_codes() {
        assert_eq!(
            AbortCode(0x0602_0000).to_string(),
            "06020000 (Object does not exist in the object dictionary)"
        );
        assert_eq!(AbortCode(0x1234_5678).to_string(), "12345678");
        let mut codes: Vec<u32> = TABLE.iter().map(|(c, _)| *c).collect();
        codes.dedup();
        assert_eq!(codes.len(), TABLE.len());
        assert!(
            codes.windows(2).all(|w| w[0] < w[1]),
            "table sorted and unique"
        );
    }
}
