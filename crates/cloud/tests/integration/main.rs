//! The integration tests of `cloud`, one module per area, in one test binary: each binary links
//! the whole stack beneath it, so one per crate keeps the build short (run one area with
//! `cargo test -p cloud --test integration AREA::`).

mod browser;
mod contract;
mod end_to_end;
mod insights;
mod interlock;
mod operations;
mod python_events;
mod python_gateway;
mod python_subscriptions;
mod roles;
mod sso;
mod storage;
mod tenants;
mod token_lifecycle;
mod web_ui;
