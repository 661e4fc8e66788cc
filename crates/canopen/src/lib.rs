//! CiA 301 CANopen, sans-IO.
//!
//! One module per service, each a sans-IO state machine driven by frames and explicit time:
//! data types ([`types`]), the object dictionary ([`od`]), CiA 306 files ([`eds`]), SDO
//! ([`sdo`]), NMT ([`nmt`]), heartbeat ([`heartbeat`]), EMCY ([`emcy`]), SYNC ([`sync`]) and TIME
//! ([`time`]); the pre-defined connection set ([`cob`]) and the frame decoder for bus monitors
//! ([`monitor`]). The tokio edge is [`driver`] (feature `tokio`, on by default).

#[cfg(feature = "tokio")]
mod alarm;
pub mod cob;
#[cfg(feature = "tokio")]
pub mod driver;
pub mod eds;
pub mod emcy;
pub mod guarding;
pub mod heartbeat;
pub mod lss;
#[cfg(feature = "tokio")]
pub mod master;
pub mod monitor;
pub mod nmt;
#[cfg(feature = "tokio")]
pub mod node;
pub mod od;
pub mod pdo;
pub mod sdo;
pub mod storage;
pub mod sync;
mod tick;
pub mod time;
pub mod types;
