//! The cloud portal: the server side of the NXg CANopen-Lift Connector.

#![warn(missing_docs)]

pub mod api;
pub mod client;
pub mod config;
pub mod devpki;
pub mod gateways;
pub mod server;
pub mod store;
pub mod web;
