//! The cloud portal: the server side of the NXg CANopen-Lift Connector — the gateways'
//! connections and registry ([`gateways`]), bus events and alarms with their webhooks
//! ([`alarms`]), who may do what ([`auth`]), the operator REST API ([`api`]) and the web UI
//! ([`web`]) over one shared [`state`], the operators' client ([`client`]), and the one TLS
//! port serving them all ([`server`]). Beneath it: its vocabulary (`cloud-types`), its
//! database (`cloud-store`) and the processes of a cluster (`cloud-cluster`).

#![warn(missing_docs)]

pub mod alarms;
pub mod api;
pub mod audit;
pub mod auth;
pub mod client;
pub mod config;
pub mod connection;
pub mod csv;
pub mod devpki;
pub mod errors;
pub mod forwarded;
pub mod gateways;
pub mod insights;
mod memory;
pub mod metrics;
pub mod outbound;
pub mod request_body;
pub mod server;
pub mod sse;
pub mod state;
pub mod throttle;
pub mod web;
