//! CiA 301 CANopen (with CiA 305 LSS and CiA 306 files), sans-IO at the core.
//!
//! One module per service, each a state machine driven by frames and explicit time that returns
//! frames and its next deadline: data types ([`types`]), the object dictionary ([`od`]), CiA 306
//! files ([`eds`]), SDO ([`sdo`]), NMT ([`nmt`]), heartbeat ([`heartbeat`]), node and life
//! guarding ([`guarding`]), EMCY ([`emcy`]), SYNC ([`sync`]), TIME ([`time`]), PDO ([`pdo`]),
//! LSS ([`lss`]) and parameter storage ([`storage`]); the pre-defined connection set ([`cob`]),
//! bus-monitor decoding ([`monitor`]) and network supervision — node states, EMCY, bus state —
//! ([`supervisor`]).
//!
//! [`node::Node`] composes them into a device, sans-IO too; [`objects`] names the
//! communication objects.
//!
//! The tokio edge (feature `tokio`, on by default): `node::LocalNode` runs a device,
//! [`master::Master`] commands a network, `sdo::clients::SdoClients` and `sdo::serve::serve_sdo`
//! do SDO alone, [`wake`] wakes their loops at their cores' deadlines.

#![warn(missing_docs)]

pub mod ascii;
pub mod cob;
pub mod eds;
pub mod emcy;
pub mod guarding;
pub mod heartbeat;
pub mod lss;
#[cfg(feature = "tokio")]
pub mod master;
pub mod monitor;
pub mod nmt;
pub mod node;
pub mod objects;
pub mod od;
pub mod pdo;
pub mod sdo;
pub mod storage;
pub mod supervisor;
pub mod sync;
mod tick;
pub mod time;
pub mod types;
#[cfg(feature = "tokio")]
pub mod wake;
