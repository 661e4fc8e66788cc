//! The integration tests of `gateway`, one module per area, in one test binary: each binary links
//! the whole stack beneath it, so one per crate keeps the build short (run one area with
//! `cargo test -p gateway --test integration AREA::`).

mod common;
mod conformance;
mod embedded;
mod events;
mod nodes;
mod python_portal;
mod robustness;
