//! The subcommands of `canlift`.

pub mod bench;
pub mod bench_gateway;
pub mod bench_portal;
pub mod cloud;
pub mod demo;
pub mod dump;
pub mod gateway;
pub mod hub;
pub mod loadgen;
pub mod nmt;
pub mod operator;
pub mod sdo;
pub mod sim;
