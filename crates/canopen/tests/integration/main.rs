//! The integration tests of `canopen`, one module per area, in one test binary: each binary links
//! the whole stack beneath it, so one per crate keeps the build short (run one area with
//! `cargo test -p canopen --test integration AREA::`).

mod common;
mod lss;
mod node_master;
mod python_canopen;
mod python_nmt;
mod python_pdo;
