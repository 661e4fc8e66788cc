//! The NXg CANopen-Lift Connector (NXg SW003 v1.0.0) with the readings of docs/PROTOCOL.md:
//! the messages as types ([`msg`]), the multiplexer text ([`mplex`]), the metadata vocabulary
//! ([`meta`]), abort codes with their messages per language ([`codes`]), and both sides of a
//! connection as sans-IO state machines: the gateway's ([`gateway`], feature `gateway`, which
//! brings the CiA 301 data types of the `canopen` crate) and the portal's ([`portal`]).
//!
//! Without the `gateway` feature the crate needs no CANopen stack: that is what a portal uses.

#![warn(missing_docs)]

pub mod codes;
pub mod digest;
#[cfg(feature = "gateway")]
pub mod gateway;
pub mod meta;
pub mod mplex;
pub mod msg;
pub mod names;
pub mod portal;

use std::time::Duration;

/// How long a connection may be silent before either side drops it: 2 × the heartbeat interval
/// + 30 s, pings and pongs counting as traffic (docs/PROTOCOL.md §Heartbeat).
pub fn silence_limit(heartbeat: Duration) -> Duration {
    heartbeat * 2 + Duration::from_secs(30)
}
