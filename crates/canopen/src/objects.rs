//! The indices of the communication profile area (CiA 301 §7.5.2), named once: the node core,
//! the master, the gateway and the tools address these objects by name.

/// Device type (UNSIGNED32; the profile number in the low 16 bits).
pub const DEVICE_TYPE: u16 = 0x1000;
/// Error register (UNSIGNED8).
pub const ERROR_REGISTER: u16 = 0x1001;
/// Pre-defined error field: the error history, newest first.
pub const ERROR_HISTORY: u16 = 0x1003;
/// COB-ID SYNC.
pub const SYNC_COB_ID: u16 = 0x1005;
/// Communication cycle period (µs).
pub const SYNC_PERIOD: u16 = 0x1006;
/// Synchronous window length (µs).
pub const SYNC_WINDOW: u16 = 0x1007;
/// Manufacturer device name.
pub const DEVICE_NAME: u16 = 0x1008;
/// Manufacturer hardware version.
pub const HARDWARE_VERSION: u16 = 0x1009;
/// Manufacturer software version.
pub const SOFTWARE_VERSION: u16 = 0x100A;
/// Guard time (ms).
pub const GUARD_TIME: u16 = 0x100C;
/// Life time factor.
pub const LIFE_TIME_FACTOR: u16 = 0x100D;
/// Store parameters.
pub const STORE: u16 = 0x1010;
/// Restore default parameters.
pub const RESTORE: u16 = 0x1011;
/// COB-ID time stamp object (bit 31 consumer, bit 30 producer).
pub const TIME_COB_ID: u16 = 0x1012;
/// COB-ID EMCY.
pub const EMCY_COB_ID: u16 = 0x1014;
/// Inhibit time EMCY (100 µs).
pub const EMCY_INHIBIT: u16 = 0x1015;
/// Consumer heartbeat time (one entry per monitored node).
pub const CONSUMER_HEARTBEAT: u16 = 0x1016;
/// Producer heartbeat time (ms).
pub const PRODUCER_HEARTBEAT: u16 = 0x1017;
/// Identity object: vendor-ID, product code, revision number, serial number.
pub const IDENTITY: u16 = 0x1018;
/// Synchronous counter overflow value.
pub const SYNC_OVERFLOW: u16 = 0x1019;
/// The first SDO server parameter (the default channel); further ones follow up to 127Fh.
pub const SDO_SERVER: u16 = 0x1200;
/// The first SDO client parameter; further ones follow up to 12FFh.
pub const SDO_CLIENT: u16 = 0x1280;
