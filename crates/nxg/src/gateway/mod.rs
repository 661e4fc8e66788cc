//! The elevator gateway's side of a connection (NXg SW003 §5–§7): its [`Settings`] with the
//! owner's write [`Policy`], where it learns what objects are ([`Metadata`]), the elevation
//! [`Lockout`] and the [`EventQueue`] all its connections share, how it builds answers, and the
//! sans-IO [`Session`].

mod answer;
mod events;
mod lockout;
mod metadata;
mod policy;
mod session;
mod settings;

use std::sync::{Arc, Mutex};

pub use events::{BusEvent, EventQueue, Happening, QUEUED_EVENTS};
pub use lockout::{Failed, LevelState, Lockout, LockoutState, FIRST_LOCK};
pub use metadata::{bare, Lookup, Metadata, Target};
pub use policy::{Policy, RemoteWrites, Rule};
pub use session::{CloseReason, Job, JobId, JobResult, Output, Phase, Session};
pub use settings::{Identity, Settings};

/// What every connection of one gateway shares: where metadata comes from, the elevation
/// lock-out and the bus events waiting for a portal (a reconnecting portal finds both where it
/// left them).
#[derive(Clone)]
pub struct Context {
    /// Descriptions of the objects.
    pub metadata: Arc<dyn Metadata>,
    /// Wrong password hashes and locks, per level.
    pub lockout: Arc<Mutex<Lockout>>,
    /// Bus events not yet delivered.
    pub events: Arc<Mutex<EventQueue>>,
}

impl Context {
    /// A context over `metadata` with a fresh lock-out and an empty event queue.
    pub fn new(metadata: Arc<dyn Metadata>) -> Context {
        Context {
            metadata,
            lockout: Arc::default(),
            events: Arc::default(),
        }
    }
}
