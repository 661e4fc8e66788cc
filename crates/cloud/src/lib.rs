//! The cloud portal: the server side of the NXg CANopen-Lift Connector — the gateways'
//! connections and registry ([`gateways`]), bus events and alarms with their webhooks
//! ([`alarms`]), the store ([`store`]) with users and roles, who elevated which lift
//! ([`elevation`]), the operator REST API
//! ([`api`], its bodies in [`rest`]) with its client ([`client`]), the web UI ([`web`]), the
//! one TLS port serving them all ([`server`]) and the processes of a cluster ([`cluster`]).

#![warn(missing_docs)]

pub mod alarms;
pub mod api;
pub mod auth;
pub mod client;
pub mod config;
pub mod devpki;
pub mod errors;
pub mod gateways;
mod memory;
pub mod server;
pub mod state;
pub mod throttle;
mod timer;
pub mod web;
