//! The integration tests of `tls`, one module per area, in one test binary: each binary links
//! the whole stack beneath it, so one per crate keeps the build short (run one area with
//! `cargo test -p tls --test integration AREA::`).

mod stream;
