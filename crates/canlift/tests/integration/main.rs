//! The integration tests of `canlift`, one module per area, in one test binary: each binary links
//! the whole stack beneath it, so one per crate keeps the build short (run one area with
//! `cargo test -p canlift --test integration AREA::`).

mod ascii_cli;
#[cfg(feature = "portal")]
mod cluster;
mod common;
#[cfg(feature = "portal")]
mod cross_gateway;
#[cfg(feature = "portal")]
mod demo_smoke;
#[cfg(feature = "portal")]
mod docs_config;
#[cfg(feature = "portal")]
mod docs_run;
mod dump_cli;
#[cfg(feature = "portal")]
mod faults;
mod gateway_cli;
mod gateway_field;
#[cfg(feature = "portal")]
mod loadgen_cli;
mod lss_cli;
mod nmt_cli;
#[cfg(feature = "portal")]
mod portal_cli;
mod sdo_cli;
#[cfg(feature = "portal")]
mod service;
mod sim_cli;
mod tools_cli;
