//! CiA 301 CANopen, sans-IO.
//!
//! So far: the pre-defined connection set ([`cob`]), SDO abort codes ([`sdo::abort`]) and the
//! frame decoder for bus monitors ([`monitor`]). The object dictionary, SDO, NMT, heartbeat,
//! EMCY, SYNC, TIME, PDO and LSS services follow the layout of DESIGN.md §2.

pub mod cob;
#[cfg(feature = "tokio")]
pub mod driver;
pub mod eds;
pub mod monitor;
pub mod od;
pub mod sdo;
pub mod types;
