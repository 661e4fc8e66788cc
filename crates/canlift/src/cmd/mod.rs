//! The subcommands of `canlift`.

#[cfg(feature = "portal")]
pub mod alarms;
pub mod bench;
#[cfg(feature = "portal")]
pub mod bench_alarms;
#[cfg(feature = "portal")]
pub mod bench_gateway;
#[cfg(feature = "portal")]
pub mod bench_portal;
#[cfg(feature = "portal")]
pub mod cloud;
#[cfg(feature = "portal")]
pub mod demo;
pub mod dump;
pub mod gateway;
pub mod hub;
pub mod loadgen;
pub mod nmt;
#[cfg(feature = "portal")]
pub mod operator;
pub mod sdo;
pub mod sim;
