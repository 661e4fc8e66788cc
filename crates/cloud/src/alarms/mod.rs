//! Faults that reach people (docs/PORTAL.md §Alarms): the portal stores every bus event its
//! gateways push (docs/PROTOCOL.md §Events) and keeps **alarms** — fault conditions with
//! a lifecycle: raised → acknowledged (by whom, when, with what comment) → cleared (the
//! condition is gone). The conditions: an EMCY of a node (per node and error code), a node that
//! fell silent, a network in trouble, and a lift whose gateway has been offline for
//! `[alarms] offline_after_s` (which needs no events, so api-1 gateways have it too).
//!
//! [`rules`] decides, sans-IO, what an event means for the alarms; [`service`] applies it to the
//! store and tells live viewers and [`webhook`] receivers.

pub mod rules;
pub mod service;
pub mod webhook;

pub use service::Alarms;
