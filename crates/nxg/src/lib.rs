//! The NXg CANopen-Lift Connector (NXg SW003 v1.0.0) with the readings of DESIGN.md §4: the
//! multiplexer text ([`mplex`]), JSON-RPC 2.0 envelopes ([`rpc`]), CANopen abort codes with their
//! messages per language ([`errors`]), and the gateway's side of a connection as a sans-IO state
//! machine ([`gateway`]), and the portal's side of a gateway connection ([`portal`]).

#![warn(missing_docs)]

pub mod errors;
pub mod gateway;
pub mod mplex;
pub mod portal;
pub mod rpc;
