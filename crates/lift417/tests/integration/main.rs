//! The integration tests of `lift417`, one module per area, in one test binary: each binary links
//! the whole stack beneath it, so one per crate keeps the build short (run one area with
//! `cargo test -p lift417 --test integration AREA::`).

mod sim_bus;
