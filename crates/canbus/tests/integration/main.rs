//! The integration tests of `canbus`, one module per area, in one test binary: each binary links
//! the whole stack beneath it, so one per crate keeps the build short (run one area with
//! `cargo test -p canbus --test integration AREA::`).

mod common;
mod hub;
mod python_can;
mod socketcan;
